"""The synthesis-method contract: one registry read by the CLI and the evaluation, one options object,
one minimum speech length, and a summary that says when the repeat guard was relaxed."""
from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

from gesturedb.errors import ParameterError
from gesturedb.synth import MIN_SPEECH_S, Searcher, SearchOptions, SynthOptions, methods
from gesturedb.synth.graph import GraphOptions, GraphSynthesizer
from gesturedb.synth.protocol import EvalSystem, Method, Synthesizer

WAV = "inputs/2_scott_0_2_2.wav"


@pytest.fixture()
def speech(scott_dir):
    return scott_dir / WAV


def test_registry_holds_both_methods_with_their_options_and_systems():
    assert methods.names() == ("knn", "graph")
    for m in methods.all_methods():
        assert issubclass(m.options, SynthOptions) and dataclasses.is_dataclass(m.options)
        assert methods.get(m.name) is m
    assert methods.get("knn").open is Searcher and methods.get("graph").open is GraphSynthesizer
    assert not methods.get("graph").streams
    assert [s.name for s in methods.eval_systems()] == ["ranksum_pose", "ranksum_audio", "graph"]
    with pytest.raises(ParameterError, match=r"method: expected one of knn, graph, got 'nn'"):
        methods.get("nn")


def test_eval_and_cli_list_what_the_registry_holds():
    from gesturedb.cli.main import make_parser
    from gesturedb.eval.common import BASELINES, SYSTEM_LABELS, SYSTEMS
    from gesturedb.eval.report import _COLORS

    assert SYSTEMS == ("ground_truth", *BASELINES, *(s.name for s in methods.eval_systems()))
    assert all(s in SYSTEM_LABELS and s in _COLORS for s in SYSTEMS)
    args = make_parser().parse_args(["synth", "db.h5", "--audio", "a.wav", "-o", "o.bvh", "--method", "graph"])
    assert args.method == "graph"


class _Echo:
    """A third method: plays the database from frame 0 (enough to show what registering takes)."""

    def __init__(self, db):
        self.db = db

    def synthesize(self, audio, *, sr=None, transcript=None, options=None, **changes):
        from gesturedb.synth import inputs
        from gesturedb.synth.result import SynthResult

        SynthOptions.of(options, **changes)
        samples, sr, path = inputs.speech_samples(self.db, audio, sr)
        T = inputs.check_speech(samples.shape[0], sr, self.db.fps, audio=path)
        src = np.arange(T, dtype=np.int64) % self.db.n_frames
        motion = Searcher(self.db).assemble(src, np.array([0]))
        return SynthResult(motion=motion, source_frames=src, boundaries=np.zeros(0, np.int64),
                           steps=[{"step": 0, "out_start": 0, "out_end": T, "control": None, "keyword": None}],
                           fps=self.db.fps, audio_path=path, options={"method": "echo"})


@pytest.fixture()
def echo_method():
    m = methods.register(Method(name="echo", summary="the database from its first frame", options=SynthOptions,
                                open=_Echo, systems=(EvalSystem("echo", "echo", "#000000"),)))
    yield m
    methods._REGISTRY.pop("echo")


def test_a_third_method_is_one_registration(echo_method, scott_db_path, speech, tmp_path, capsys):
    from gesturedb.cli.main import main

    assert methods.names()[-1] == "echo" and methods.system_method("echo") == (echo_method, echo_method.systems[0])
    with pytest.raises(ParameterError, match="already registered"):
        methods.register(echo_method)
    out = tmp_path / "e.bvh"
    assert main(["synth", str(scott_db_path), "--method", "echo", "--audio", str(speech), "-o", str(out)]) == 0
    assert json.loads((tmp_path / "e.provenance.json").read_text())["options"]["method"] == "echo"
    assert isinstance(echo_method.open(None), Synthesizer)
    # a flag the method has no option for is refused by name, before anything is read
    capsys.readouterr()
    assert main(["synth", str(scott_db_path), "--method", "echo", "--audio", str(speech), "-o", str(out),
                 "--step", "4"]) == 2
    assert "--method echo: --step works with --method knn only" in capsys.readouterr().err


def test_options_object_and_keywords_give_the_same_frames(scott_db, speech):
    s = Searcher(scott_db)
    opts = SearchOptions(seed=3, control="0-20: left_wrist_height > p60", seam_decay_s=0.3)
    a = s.synthesize(speech, options=opts)
    b = s.synthesize(speech, seed=3, control="0-20: left_wrist_height > p60", seam_decay_s=0.3)
    c = s.synthesize(speech, options=opts.replace(seed=0), seed=3)  # keywords override the object
    for r in (b, c):
        assert np.array_equal(a.source_frames, r.source_frames)
        assert np.array_equal(a.motion.rotations, r.motion.rotations)
        assert a.options == r.options


def test_options_have_named_defaults_and_refuse_unknown_names(scott_db):
    from gesturedb.search import STEP_FRAMES
    from gesturedb.synth.options import default_step

    o = SearchOptions()
    assert o.step is None and o.step_at(15.0) == STEP_FRAMES == 8 and o.step_at(30.0) == default_step(30.0) == 16
    with pytest.raises(ParameterError, match=r"SearchOptions: unknown option stepp; expected some of .*step"):
        o.replace(stepp=4)
    with pytest.raises(ParameterError, match=r"SearchOptions: unknown option gap_s"):
        Searcher(scott_db).synthesize(np.zeros(16000, np.float32), sr=16000, gap_s=0.3)
    # the shared fields carry over from one method's options to another's, the others take their defaults
    g = GraphOptions.of(SearchOptions(seam_decay_s=0.2, keywords=False, exclude=["a"], seed=5))
    assert (g.seam_decay_s, g.keywords, g.exclude, g.gap_s) == (0.2, False, ["a"], None)
    with pytest.raises(ParameterError, match="options: expected a GraphOptions"):
        GraphOptions.of({"gap_s": 0.3})


def test_every_method_refuses_speech_shorter_than_one_step_with_one_message(scott_db):
    short = np.zeros(int(16000 * 0.2), np.float32)
    msg = (r"audio: expected at least one search step \(8 frames = 0.53 s\), got 3 frames \(0.20 s\): "
           rf"every synthesis method needs {MIN_SPEECH_S:.2f} s of speech")
    for m in methods.all_methods():
        with pytest.raises(ParameterError, match=msg):
            m.open(scott_db).synthesize(short, sr=16000)
    # exactly the minimum is enough for both
    ok = np.random.default_rng(0).standard_normal(int(np.ceil(16000 * MIN_SPEECH_S)) + 1).astype(np.float32) * 0.1
    for m in methods.all_methods():
        assert m.open(scott_db).synthesize(ok, sr=16000).n_frames == 8


def test_guard_summary_counts_relaxed_steps():
    from gesturedb.cli.synth import guard_summary

    assert guard_summary({"guard_s": 4.0, "guard_relaxed": 0, "steps": 117}) == "repeat guard 4 s"
    assert guard_summary({"guard_s": 4.0, "guard_relaxed": 70, "steps": 117}) == \
        "repeat guard 4 s, relaxed on 70 of 117 steps where it left no candidate"
    assert guard_summary({"guard_s": 0.0, "guard_relaxed": 0, "steps": 9}) == "repeat guard off"


def test_cli_summary_says_how_often_the_guard_was_relaxed(scott_db_path, speech, tmp_path, capsys):
    from gesturedb.cli.main import main

    out = tmp_path / "r.bvh"
    # a narrow control: few windows, so the guard must give way on some steps
    assert main(["synth", str(scott_db_path), "--audio", str(speech), "-o", str(out),
                 "--control", "left_wrist_height > p97"]) == 0
    printed = capsys.readouterr().out
    prov = json.loads((tmp_path / "r.provenance.json").read_text())
    n = sum(s["guard_relaxed"] for s in prov["steps"])
    assert n == prov["repeats"]["guard_relaxed"] > 0
    assert f"repeat guard 4 s, relaxed on {n} of {len(prov['steps'])} steps" in printed, printed
