"""The studio's leftovers on the server side (issue 39): a timeline block plays its source stretch with the
recording's own speech (``GET /source?format=wav``), or says why it cannot; three.js's glTF loader is served
where its own import finds the page's three.js."""
from __future__ import annotations

import io
import os
import shutil
import sys
import wave

import numpy as np
import pytest

pytest.importorskip("starlette")

from starlette.testclient import TestClient  # noqa: E402

import gesturedb  # noqa: E402
from gesturedb.db import schema  # noqa: E402
from gesturedb.io import read_audio  # noqa: E402
from gesturedb.serve import create_app  # noqa: E402
from gesturedb.serve.vendor import find_gltf_loader, find_three  # noqa: E402

sys.path.insert(0, os.path.dirname(__file__))
from serve_double import ReplayStream  # noqa: E402


@pytest.fixture(scope="module")
def client(scott_db_path):
    with gesturedb.open(scott_db_path) as db, TestClient(create_app(db, stream_factory=ReplayStream)) as c:
        yield c, db


def test_source_speech_is_the_recordings_own_samples(client):
    c, db = client
    rec = db.recordings[0]
    r = c.get("/source", params={"recording": rec.name, "start_s": 0.5, "end_s": 1.7, "format": "wav"})
    assert r.status_code == 200 and r.headers["content-type"] == "audio/wav"
    with wave.open(io.BytesIO(r.content)) as w:
        sr, n, ch, width = w.getframerate(), w.getnframes(), w.getnchannels(), w.getsampwidth()
        got = np.frombuffer(w.readframes(n), dtype="<i2")
    x, file_sr = read_audio(rec.audio_path, sr=None)
    assert (sr, ch, width) == (file_sr, 1, 2) and n == round(1.7 * sr) - round(0.5 * sr)
    want = np.round(np.clip(x[round(0.5 * sr):round(1.7 * sr)], -1, 1) * 32767).astype(np.int16)
    assert np.array_equal(got, want)
    # the frames of the same stretch: one per 1/fps s of that speech
    frames = c.get("/source", params={"recording": rec.name, "start_s": 0.5, "end_s": 1.7})
    assert frames.status_code == 200 and int.from_bytes(frames.content[12:16], "little") == round(1.2 * db.fps)


def test_source_speech_that_is_not_on_the_server_says_so(scott_db_path, tmp_path):
    moved = tmp_path / "moved.h5"
    shutil.copy(scott_db_path, moved)
    import h5py

    with h5py.File(moved, "r+") as h5:
        paths = h5[schema.RECORDING_AUDIO_PATH]
        paths[0] = "gone/2_scott_0_1_1.wav"
    with gesturedb.open(moved) as db, TestClient(create_app(db, stream_factory=ReplayStream)) as c:
        name = db.recordings[0].name
        r = c.get("/source", params={"recording": name, "start_s": 0, "end_s": 1, "format": "wav"})
        assert r.status_code == 404 and r.json()["error"] == "no_audio"
        assert r.json()["message"] == (f"recording {name!r}: its speech file 'gone/2_scott_0_1_1.wav' (as the build "
                                       f"was given it) is not on this server")
        bad = c.get("/source", params={"recording": name, "start_s": 0, "end_s": 1, "format": "mp3"})
        assert bad.status_code == 400 and bad.json()["message"] == "format: expected frames or wav; got 'mp3'"
        late = c.get("/source", params={"recording": name, "start_s": 0, "end_s": 999, "format": "wav"})
        assert late.status_code == 400 and "expected 0 <= start_s < end_s" in late.json()["message"]


def test_gltf_loader_is_served_beside_the_pages_three_js(client):
    c, _ = client
    three = find_three()
    if three is None:
        pytest.skip("Debian's libjs-three is not installed")
    assert c.get("/health").json()["gltf_loader"] is (find_gltf_loader(three) is not None)
    if find_gltf_loader(three) is None:
        pytest.skip("this three.js has no examples/jsm/loaders/GLTFLoader.js")
    loader = c.get("/vendor/three/examples/jsm/loaders/GLTFLoader.js")
    assert loader.status_code == 200 and "javascript" in loader.headers["content-type"]
    # its one import, resolved from where it is served, is the three.js the page imports
    assert '} from "../../../build/three.module.js";' in loader.text
    page = c.get("/studio/studio.js").text
    assert "import('/vendor/three/build/three.module.js')" in page
    assert c.get("/vendor/three/build/three.module.js").content == open(three, "rb").read()
