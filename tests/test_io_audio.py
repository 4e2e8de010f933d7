"""read_audio on the real WAVs (32-bit float and PCM16) and generated files."""
from __future__ import annotations

import struct

import numpy as np
import pytest
import soundfile as sf

from gesturedb.errors import InputFileError, ParameterError
from gesturedb.io import read_audio


def test_real_float32_wav_needs_no_resampling(scott_dir):
    path = scott_dir / "2_scott_0_1_1.wav"
    assert sf.info(str(path)).subtype == "FLOAT"  # format tag 3: the wave module cannot read it
    x, sr = read_audio(path)
    ref, ref_sr = sf.read(str(path), dtype="float32")
    assert sr == ref_sr == 16000 and x.dtype == np.float32 and x.ndim == 1
    np.testing.assert_array_equal(x, ref)
    assert abs(len(x) / sr - 64.097) < 0.01
    assert 0.001 < np.sqrt(np.mean(x.astype(np.float64) ** 2)) < 0.5  # speech, not silence or clipping


def test_real_pcm16_wav_and_resampling(scott_dir):
    path = scott_dir / "inputs" / "2_scott_0_2_2.wav"
    assert sf.info(str(path)).subtype == "PCM_16"
    x, sr = read_audio(path)
    ref, _ = sf.read(str(path), dtype="float32")
    np.testing.assert_array_equal(x, ref)
    y, sr8 = read_audio(path, sr=8000)
    assert sr8 == 8000 and abs(len(y) - len(x) / 2) <= 1
    assert read_audio(path, sr=8000.0)[1] == 8000
    # downsampling keeps the low band: the envelopes agree
    env_x = np.abs(x[: len(y) * 2]).reshape(-1, 800).mean(axis=1)
    env_y = np.abs(y[: len(env_x) * 400]).reshape(-1, 400).mean(axis=1)
    assert np.corrcoef(env_x, env_y)[0, 1] > 0.95


def test_pcm24_stereo_44k_is_mixed_to_mono_and_resampled(tmp_path):
    sr_in, dur = 44100, 1.5
    t = np.arange(int(sr_in * dur)) / sr_in
    left = 0.5 * np.sin(2 * np.pi * 440.0 * t)
    right = 0.3 * np.sin(2 * np.pi * 440.0 * t)
    path = tmp_path / "stereo24.wav"
    sf.write(str(path), np.stack([left, right], axis=1), sr_in, subtype="PCM_24")
    native, sr_native = read_audio(path, sr=None)
    assert sr_native == 44100
    np.testing.assert_allclose(native, 0.4 * np.sin(2 * np.pi * 440.0 * t), atol=1e-6)
    x, sr = read_audio(path, sr=16000)
    assert sr == 16000 and x.dtype == np.float32
    assert abs(len(x) - dur * 16000) <= 1
    spec = np.abs(np.fft.rfft(x[2000:-2000] * np.hanning(len(x) - 4000)))
    freqs = np.fft.rfftfreq(len(x) - 4000, 1 / 16000)
    assert abs(freqs[np.argmax(spec)] - 440.0) < 2.0
    assert abs(np.max(np.abs(x[2000:-2000])) - 0.4) < 0.01


def test_silence_is_fine(tmp_path):
    path = tmp_path / "silence.wav"
    sf.write(str(path), np.zeros(16000), 16000, subtype="PCM_16")
    x, sr = read_audio(path)
    assert len(x) == 16000 and not x.any()


def test_empty_garbage_missing_and_nan(tmp_path):
    empty = tmp_path / "empty.wav"
    sf.write(str(empty), np.zeros((0, 1)), 16000, subtype="PCM_16")
    with pytest.raises(InputFileError, match=r"no audio samples \(0 frames"):
        read_audio(empty)
    garbage = tmp_path / "garbage.wav"
    garbage.write_bytes(b"RIFF\x00\x00\x00\x00WAVEjunkjunkjunk" * 3)
    with pytest.raises(InputFileError, match="cannot read as audio") as err:
        read_audio(garbage)
    assert str(err.value).startswith(str(garbage))
    with pytest.raises(InputFileError, match="no such file"):
        read_audio(tmp_path / "missing.wav")
    bad = tmp_path / "nan.wav"
    data = np.zeros(1000, dtype=np.float32)
    data[480] = np.nan
    sf.write(str(bad), data, 16000, subtype="FLOAT")
    with pytest.raises(InputFileError, match=r"sample 480 \(t = 0.030 s, channel 0\) is not finite"):
        read_audio(bad)


def test_float_wav_written_by_hand_with_format_tag_3(tmp_path):
    """A minimal IEEE-float WAV header (what BEAT2 ships), independent of libsndfile's writer."""
    samples = (0.25 * np.sin(np.linspace(0, 20, 800))).astype("<f4")
    fmt = struct.pack("<HHIIHH", 3, 1, 16000, 16000 * 4, 4, 32)
    body = b"fmt " + struct.pack("<I", len(fmt)) + fmt + b"data" + struct.pack("<I", samples.nbytes) + samples.tobytes()
    path = tmp_path / "tag3.wav"
    path.write_bytes(b"RIFF" + struct.pack("<I", 4 + len(body)) + b"WAVE" + body)
    x, sr = read_audio(path)
    assert sr == 16000
    np.testing.assert_array_equal(x, samples)


@pytest.mark.parametrize("sr", [0, -16000, 16000.5, True, "16k"])
def test_bad_rate(tmp_path, sr):
    with pytest.raises(ParameterError, match="sr: expected a positive integer"):
        read_audio(tmp_path / "whatever.wav", sr=sr)


def test_audio_duration_reads_the_header_only(scott_dir, tmp_path):
    """The length the build's automatic gap uses: that of the decoded samples, from the header;
    a missing or unreadable file is the same one-line error as read_audio's."""
    from gesturedb.errors import InputFileError
    from gesturedb.io.audio import audio_duration, read_audio

    wav = scott_dir / "2_scott_0_1_1.wav"
    x, sr = read_audio(wav, sr=None)
    assert audio_duration(wav) == x.shape[0] / sr
    with pytest.raises(InputFileError, match="no such file"):
        audio_duration(tmp_path / "missing.wav")
    bad = tmp_path / "bad.wav"
    bad.write_bytes(b"RIFF\x00\x00\x00\x00WAVEjunk")
    with pytest.raises(InputFileError, match=r"bad\.wav.*cannot read as audio"):
        audio_duration(bad)
