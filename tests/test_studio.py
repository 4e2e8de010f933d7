"""The browser studio in Debian's chromium (headless, driven by selenium through chromium-driver).

The page loads with no console errors, the fake microphone streams real speech,
frames arrive, screenshots taken seconds apart differ where the body is, a
toggled mask appears in the provenance timeline, the result can be downloaded,
and a WAV file played through the page streams too. Screenshots are kept in
out/studio-*.png for a person to look at.

The server is uvicorn in this process on the real database; its stream is
gesturedb.synth.stream.Stream where that exists, else the test double of the
agreed interface (tests/serve_double.py).
"""
from __future__ import annotations

import os
import shutil
import sys
import time
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("starlette")
pytest.importorskip("selenium")

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "out"
CHROMIUM = shutil.which("chromium")
DRIVER = shutil.which("chromedriver")

pytestmark = [pytest.mark.slow,
              pytest.mark.skipif(not (CHROMIUM and DRIVER), reason="Debian's chromium and chromium-driver are not "
                                 "installed (scripts/setup.sh --tests installs them)")]

sys.path.insert(0, os.path.dirname(__file__))


def _factory():
    try:
        from gesturedb.synth.stream import Stream
        return Stream, "gesturedb.synth.stream.Stream"
    except ImportError:
        from serve_double import ReplayStream
        return ReplayStream, "the test double (gesturedb.synth.stream is not there yet)"


@pytest.fixture(scope="module")
def server(scott_db_path):
    import gesturedb
    from gesturedb.serve import Limits, create_app
    from test_serve import LiveServer

    factory, what = _factory()
    print(f"studio test streams with {what}")
    lim = Limits()
    with gesturedb.open(scott_db_path) as db, LiveServer(create_app(db, stream_factory=factory, limits=lim), lim) as s:
        yield s


@pytest.fixture(scope="module")
def speech_wav(scott_dir, tmp_path_factory):
    """25 s of the real recording as a 48 kHz PCM16 WAV (what chromium's fake microphone plays, looping)."""
    import soundfile as sf

    from gesturedb.io import read_audio

    x, sr = read_audio(scott_dir / "2_scott_0_1_1.wav", sr=48000)
    path = tmp_path_factory.mktemp("studio") / "speech.wav"
    sf.write(path, x[5 * sr: 30 * sr], sr, subtype="PCM_16")
    return path


@pytest.fixture(scope="module")
def browser(speech_wav):
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    os.environ.setdefault("SE_OFFLINE", "true")  # never let selenium fetch a browser or a driver
    opts = webdriver.ChromeOptions()
    opts.binary_location = CHROMIUM
    for a in ["--headless=new", "--no-sandbox", "--disable-dev-shm-usage", "--window-size=1280,860",
              "--use-fake-ui-for-media-stream", "--use-fake-device-for-media-stream",
              f"--use-file-for-fake-audio-capture={speech_wav}", "--autoplay-policy=no-user-gesture-required",
              "--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--mute-audio"]:
        opts.add_argument(a)
    opts.set_capability("goog:loggingPrefs", {"browser": "ALL"})
    d = webdriver.Chrome(service=Service(DRIVER), options=opts)
    d.set_script_timeout(30)
    yield d
    d.quit()


def _wait(driver, js: str, timeout_s: float = 30.0, what: str = ""):
    t = time.monotonic()
    while time.monotonic() - t < timeout_s:
        v = driver.execute_script(f"return {js}")
        if v:
            return v
        time.sleep(0.2)
    state = driver.execute_script("const s = window.studio || {}; return {log: s.log, errors: s.errors, "
                                  "frames: s.framesReceived, closed: s.closed}")
    raise AssertionError(f"timed out waiting for {what or js}; page state: {state}")


def _severe(driver) -> list[str]:
    return [e["message"] for e in driver.get_log("browser") if e["level"] == "SEVERE"]


def _canvas_pixels(driver, path: Path) -> np.ndarray:
    from PIL import Image

    driver.save_screenshot(str(path))
    r = driver.execute_script("const b = document.getElementById('view').getBoundingClientRect(); "
                              "return [b.left, b.top, b.right, b.bottom, window.devicePixelRatio];")
    k = r[4]
    img = np.asarray(Image.open(path).convert("RGB"), dtype=np.int16)
    return img[int(r[1] * k):int(r[3] * k), int(r[0] * k):int(r[2] * k)]


def _character_glb(db_path, folder: Path, rename: dict) -> Path:
    """A rigged .glb of the test database's skeleton (gesturedb's own export: a skin, a box per bone),
    its bones named as the database's joints except those in ``rename``."""
    import gesturedb
    from gesturedb.io.gltf import write_glb
    from gesturedb.motion import Motion, Skeleton

    path = folder / ("partial.glb" if rename else "character.glb")
    with gesturedb.open(db_path) as db:
        m = db.motion(db.recordings[0].name, 0.0, 1.0)
    sk = m.skeleton
    sk = Skeleton([rename.get(n, n) for n in sk.names], sk.parents, sk.offsets, sk.channel_orders, sk.end_sites,
                  sk.length_unit_m)
    write_glb(path, Motion(skeleton=sk, fps=m.fps, rotations=m.rotations, root_positions=m.root_positions))
    return path


def _assert_whole_body_in_view(d) -> None:
    """Every joint (or character bone) drawn, head top and feet included, is inside the view, clear of its
    top and bottom edges (normalised device coordinates, -1 bottom to 1 top)."""
    lo, hi = d.execute_script("return window.studio.bodyExtent()")
    assert -0.95 < lo < hi < 0.95, f"the body reaches the view's edge: y from {lo:.3f} to {hi:.3f} of [-1, 1]"


def test_studio_streams_the_microphone_and_a_wav(server, browser, speech_wav, scott_db_path):
    OUT.mkdir(exist_ok=True)
    d = browser
    d.get(server.http + "/")
    _wait(d, "window.studio && window.studio.idlePose && document.querySelectorAll('.chip').length > 0",
          what="the page and the body's first pose")
    assert d.execute_script("return window.studio.threeLoaded"), "three.js (libjs-three) did not load"
    assert _severe(d) == []
    rest = _canvas_pixels(d, OUT / "studio-0-loaded.png")

    # the fake microphone streams speech; frames arrive and play
    d.find_element("id", "mic").click()
    _wait(d, "window.studio.ready", what="the stream's ready message")
    _wait(d, "window.studio.framesReceived > 40 && window.studio.shownFrame > 20", what="frames")
    a = _canvas_pixels(d, OUT / "studio-1.png")
    time.sleep(2.0)
    b = _canvas_pixels(d, OUT / "studio-2.png")
    moved = np.abs(a - b).sum(axis=2) > 40
    assert moved.mean() > 0.001, f"the body did not move between screenshots 2 s apart ({moved.mean():.5f} of pixels)"
    assert (np.abs(a - rest).sum(axis=2) > 40).mean() > 0.001, "the body is still in its rest pose"
    _assert_whole_body_in_view(d)

    # a toggled mask is in force from a later step, and the timeline shows it
    mask = "left_wrist_height_high"
    d.find_element("css selector", f".chip[data-mask='{mask}']").click()
    _wait(d, f"window.studio.controlAcks.some(m => m.control === '{mask}')", what="the control acknowledgement")
    _wait(d, f"window.studio.steps.some(s => s.control === '{mask}')", what="a step under the control")
    _wait(d, f"[...document.querySelectorAll('.ctl')].some(e => e.textContent === '{mask}')", what="timeline strip")
    time.sleep(1.5)
    d.save_screenshot(str(OUT / "studio.png"))

    # stop: the remaining frames, then the result to download
    d.find_element("id", "stop").click()
    done = _wait(d, "window.studio.done", what="done")
    assert done["frames"] == d.execute_script("return window.studio.framesReceived")
    href = d.find_element("id", "dl-bvh").get_attribute("href")
    assert "/result/" in href and "format=bvh" in href
    steps = d.execute_script("return window.studio.steps")
    assert steps and all(s["recording"] for s in steps)
    assert d.execute_script("return window.studio.late") <= 3  # only the start may wait for the first frames

    # a click on a window of the timeline plays its source stretch, with the recording's own speech
    # (the test database was built from the real files, which are on this machine)
    d.find_element("css selector", ".step").click()
    _wait(d, "window.studio.log.some(l => l.startsWith('playing the source'))", what="source preview")
    played = d.execute_script("return window.studio.sourcePlayed")
    assert played["audio"] is True and played["why"] is None and played["frames"] > 0, played

    # the user's character: a .glb of the database's own skeleton (what gesturedb exports) is driven
    # joint by joint; one with two bones renamed says which joints found no bone
    char = _character_glb(scott_db_path, Path(speech_wav).parent, rename={})
    d.find_element("id", "character").send_keys(str(char))
    c = _wait(d, "window.studio.character", what="the character loaded")
    assert c["matched"] == c["joints"] and c["unmatched"] == [] and abs(c["scale"] - 1) < 1e-6, c
    part = _character_glb(scott_db_path, Path(speech_wav).parent, rename={"left_wrist": "hand_l", "head": "noggin"})
    d.find_element("id", "character").send_keys(str(part))
    _wait(d, "window.studio.character && window.studio.character.name === 'partial.glb'", what="the second one")
    c = d.execute_script("return window.studio.character")
    assert sorted(c["unmatched"]) == ["head", "left_wrist"] and sorted(c["undriven"]) == ["hand_l", "noggin"], c
    msg = d.find_element("id", "character-msg").text
    assert "left_wrist" in msg and "head" in msg and f"{c['joints'] - 2} of {c['joints']} joints" in msg, msg
    d.execute_script("document.getElementById('character-msg').scrollIntoView()")
    d.save_screenshot(str(OUT / "studio-character-partial.png"))
    d.find_element("id", "character").send_keys(str(char))
    _wait(d, "window.studio.character && window.studio.character.name === 'character.glb'", what="back to the full one")

    # a WAV file played through the page streams the same way (here through the character)
    d.find_element("id", "wav").send_keys(str(speech_wav))
    _wait(d, "window.studio.mode === 'speech.wav' && window.studio.framesReceived > 40", what="frames of the WAV")
    _wait(d, "window.studio.shownFrame > 20", what="the WAV's frames playing")
    a = _canvas_pixels(d, OUT / "studio-character-1.png")
    time.sleep(1.5)
    b = _canvas_pixels(d, OUT / "studio-character-2.png")
    assert (np.abs(a - b).sum(axis=2) > 40).mean() > 0.001, "the character did not move"
    _assert_whole_body_in_view(d)
    d.find_element("id", "stop").click()
    _wait(d, "window.studio.done", what="done of the WAV")
    errors = d.execute_script("return window.studio.errors")
    assert errors == [] and _severe(d) == []


def test_studio_without_live_streaming_synthesizes_a_wav_offline(scott_db_path, browser, speech_wav, monkeypatch):
    """Where the installation cannot stream, the page says so and a WAV file is synthesized by POST /synth
    (the real k-NN search) and played in sync: real provenance in the timeline."""
    import gesturedb
    import gesturedb.serve.app as appmod
    from gesturedb.serve import Limits, create_app
    from test_serve import LiveServer

    monkeypatch.setattr(appmod, "default_stream_factory",
                        lambda: (None, "live streaming is not available in this installation (test)."))
    lim = Limits()
    with gesturedb.open(scott_db_path) as db, LiveServer(create_app(db, limits=lim), lim) as srv:
        d = browser
        d.get(srv.http + "/")
        _wait(d, "window.studio && window.studio.idlePose", what="the page")
        assert "not available" in d.find_element("id", "banner").text
        d.find_element("id", "wav").send_keys(str(speech_wav))
        n = int(np.ceil(25 * db.fps))
        _wait(d, f"window.studio.framesReceived === {n} && window.studio.shownFrame > 30", timeout_s=120,
              what="the offline result playing")
        a = _canvas_pixels(d, OUT / "studio-offline-1.png")
        time.sleep(1.5)
        b = _canvas_pixels(d, OUT / "studio-offline-2.png")
        assert (np.abs(a - b).sum(axis=2) > 40).mean() > 0.001, "the body did not move"
        steps = d.execute_script("return window.studio.steps")
        assert len(steps) == int(np.ceil(n / 8)) and {s["recording"] for s in steps} <= {r.name for r in db.recordings}
        assert all(s["pose_rank"] >= 0 and s["audio_rank"] >= 0 for s in steps)
        assert d.find_element("id", "dl-bvh").get_attribute("class") == "button"
        assert d.execute_script("return window.studio.errors") == [] and _severe(d) == []
