"""Offscreen rendering of the real clip: pixels where the joints project, video/GIF/PNG outputs."""
from __future__ import annotations

import colorsys
import re
import subprocess

import imageio.v3 as iio
import imageio_ffmpeg
import numpy as np
import pytest
import soundfile as sf

from gesturedb import render as R
from gesturedb.errors import ParameterError

SIZE = (320, 320)


@pytest.fixture(scope="module")
def scott(scott_dir):
    from gesturedb.io.smplx import read_smplx

    m = read_smplx(scott_dir / "2_scott_0_1_1.npz")
    return m.positions, np.asarray(m.skeleton.parents), list(m.skeleton.names), m.fps


def _joint_coloured(img: np.ndarray, style=R.Style()) -> np.ndarray:
    """Mask of pixels whose hue and saturation are those of the (shaded) joint colour."""
    f = img.astype(np.float64) / 255.0
    mx, mn = f.max(axis=2), f.min(axis=2)
    sat = np.where(mx > 0, (mx - mn) / np.maximum(mx, 1e-9), 0)
    r, g, b = f[..., 0], f[..., 1], f[..., 2]
    hue = np.degrees(np.arctan2(np.sqrt(3) * (g - b), 2 * r - g - b)) % 360
    target = colorsys.rgb_to_hsv(*style.joint_color)[0] * 360
    return (np.abs((hue - target + 180) % 360 - 180) < 12) & (sat > 0.55) & (mx > 0.3)


def _bone_coloured(img: np.ndarray, style=R.Style()) -> np.ndarray:
    f = img.astype(np.float64) / 255.0
    return (f[..., 2] > f[..., 0] + 0.15) & (f[..., 2] > f[..., 1] + 0.05)


def _pixel_distance_to(points_uv: np.ndarray, h: int, w: int) -> np.ndarray:
    rows, cols = np.mgrid[0:h, 0:w]
    centres = np.stack([cols + 0.5, rows + 0.5], axis=-1).reshape(-1, 1, 2)
    return np.min(np.linalg.norm(centres - points_uv[None], axis=2), axis=1).reshape(h, w)


def test_camera_keeps_the_whole_clip_in_view(scott):
    pos, parents, names, fps = scott
    cam = R.fit_camera(pos, size=SIZE)
    uv = R.project_points(cam, pos).reshape(-1, 2)
    assert np.all(np.isfinite(uv))
    assert uv[:, 0].min() > 0 and uv[:, 0].max() < SIZE[0]
    assert uv[:, 1].min() > 0 and uv[:, 1].max() < SIZE[1]
    # camera in front of the speaker (+z), looking back at the body
    assert cam.position[2] > pos[..., 2].max()
    # the body is not a speck: the clip's height fills a good part of the frame
    assert uv[:, 1].max() - uv[:, 1].min() > 0.45 * SIZE[1]
    # a smaller margin moves the camera closer, and the clip still fits
    tight = R.project_points(R.fit_camera(pos, size=SIZE, margin=1.0), pos).reshape(-1, 2)
    assert tight.min() > 0 and tight[:, 0].max() < SIZE[0] and tight[:, 1].max() < SIZE[1]
    assert np.ptp(tight[:, 1]) > 1.05 * np.ptp(uv[:, 1])
    # the speaker's left (+x) appears on the image's right, as seen from the front
    left, right = names.index("left_wrist"), names.index("right_wrist")
    k = np.argmax(pos[:, left, 0] - pos[:, right, 0])
    uvk = R.project_points(cam, pos[k, [left, right]])
    assert uvk[0, 0] > uvk[1, 0]


def test_rendered_joints_appear_where_they_project(scott):
    pos, parents, names, fps = scott
    cam = R.fit_camera(pos, size=SIZE)
    frames = [0, 700, 1400]
    with R.SkeletonRenderer(parents, cam, rest=pos[0]) as r:
        imgs = [r.render(pos[f]) for f in frames]
        # two independent projections: ours (numpy) and VTK's own camera transform
        np.testing.assert_allclose(R.project_points(cam, pos[frames[1]]), r.display_points(pos[frames[1]]), atol=1e-6)
    wrists = [names.index("left_wrist"), names.index("right_wrist")]
    h, w = SIZE[1], SIZE[0]
    for f, img in zip(frames, imgs):
        assert img.shape == (h, w, 3) and img.dtype == np.uint8
        # not blank: many colours, skeleton colours present
        assert len(np.unique(img.reshape(-1, 3), axis=0)) > 100
        joint = _joint_coloured(img)
        assert joint.sum() > 150
        assert _bone_coloured(img).sum() > 150
        uv = R.project_points(cam, pos[f])
        dist = _pixel_distance_to(uv, h, w)
        # joint-coloured pixels lie on the projected joints (spheres are a few pixels wide) ...
        assert np.all(dist[joint] < 10), f"frame {f}: joint colour {dist[joint].max():.1f} px from any joint"
        # ... and each wrist shows its sphere around its projection
        for j in wrists:
            near = _pixel_distance_to(uv[j : j + 1], h, w) < 5
            assert joint[near].sum() >= 3, f"frame {f}: no joint colour at wrist {names[j]} {uv[j]}"
        # far from every joint: background, floor or bones, never the joint colour
        assert not joint[dist > 15].any()


def test_render_frames_matches_the_renderer_and_checks_inputs(scott):
    pos, parents, _, _ = scott
    imgs = R.render_frames(pos[:40], parents, size=(160, 120), frames=[0, 39])
    assert imgs.shape == (2, 120, 160, 3) and imgs.dtype == np.uint8
    assert not np.array_equal(imgs[0], imgs[1])  # the pose changed, so the picture did
    with pytest.raises(ParameterError, match=r"parents: expected 55 integer parent indices"):
        R.render_frames(pos[:2], parents[:10])
    with pytest.raises(ParameterError, match=r"frames: expected indices in \[0, 40\)"):
        R.render_frames(pos[:40], parents, frames=[0, 40])
    with pytest.raises(ParameterError, match=r"positions: expected joint positions of shape \(F, J, 3\)"):
        R.render_frames(np.zeros((4, 55)), parents)


def _ffmpeg_info(path) -> str:
    run = subprocess.run([imageio_ffmpeg.get_ffmpeg_exe(), "-hide_banner", "-i", str(path)], capture_output=True, text=True)
    return run.stderr


def _read_mp4(path):
    gen = imageio_ffmpeg.read_frames(str(path))
    meta = next(gen)
    w, h = meta["size"]
    frames = [np.frombuffer(b, dtype=np.uint8).reshape(h, w, 3) for b in gen]
    return meta, np.stack(frames)


def test_video_outputs(scott, scott_dir, tmp_path):
    pos, parents, _, fps = scott
    n = 45
    panels = [(pos[:n], parents, "ground truth"), (pos[600 : 600 + n - 5], parents, "synthesized")]
    size = (160, 180)

    mp4 = R.render_video(tmp_path / "a.mp4", panels, fps=fps, audio=scott_dir / "2_scott_0_1_1.wav", size=size,
                         captions=[(0.0, 0.6, "hello"), (0.6, 1.4, "there")])
    meta, frames = _read_mp4(mp4)
    assert frames.shape == (n, size[1], 2 * size[0], 3)  # the shorter panel holds its last pose
    assert meta["fps"] == pytest.approx(fps)
    info = _ffmpeg_info(mp4)
    assert re.search(r"Stream #0:\d.*Video: h264", info)
    assert re.search(r"Stream #0:\d.*Audio: aac", info)
    # the audio was trimmed to the video's 1.5 s
    sr_in = sf.info(scott_dir / "2_scott_0_1_1.wav").samplerate
    wav = tmp_path / "back.wav"
    subprocess.run([imageio_ffmpeg.get_ffmpeg_exe(), "-v", "error", "-i", str(mp4), "-vn", str(wav)], check=True)
    back, sr = sf.read(wav)
    assert sr == sr_in and abs(back.shape[0] / sr - n / fps) < 0.05
    # both panels show a skeleton
    assert _joint_coloured(frames[10][:, : size[0]]).sum() > 30
    assert _joint_coloured(frames[10][:, size[0] :]).sum() > 30

    # a short audio array is padded with silence to the video length; no audio -> no stream
    short = np.sin(np.linspace(0, 2000, 8000)).astype(np.float32)
    mp4b = R.render_video(tmp_path / "b.mp4", panels[:1], fps=fps, audio=short, sr=16000, size=size, time_label=False)
    subprocess.run([imageio_ffmpeg.get_ffmpeg_exe(), "-v", "error", "-y", "-i", str(mp4b), "-vn", str(wav)], check=True)
    back, sr = sf.read(wav)
    assert abs(back.shape[0] / sr - n / fps) < 0.05
    assert np.abs(back[: sr // 4]).max() > 0.3 and np.abs(back[-sr // 4 :]).max() < 0.01
    mp4c = R.render_video(tmp_path / "c.mp4", panels[:1], fps=fps, size=size)
    assert "Audio:" not in _ffmpeg_info(mp4c)
    assert _read_mp4(mp4c)[1].shape == (n, size[1], size[0], 3)

    gif = R.render_video(tmp_path / "a.gif", panels, fps=fps, size=size)
    g = iio.imread(gif, index=None)
    assert g.shape[0] == n and g.shape[1:3] == (size[1], 2 * size[0])
    from PIL import Image

    with Image.open(gif) as im:
        assert abs(im.info["duration"] - 1000 / fps) < 10 and im.info["loop"] == 0  # whole 1/100 s, looping

    png = R.render_contact_sheet(tmp_path / "sheet.png", panels, n=6, fps=fps, size=(120, 150))
    sheet = iio.imread(png)
    assert sheet.shape[:2] == (2 * 150, 6 * 120)
    cells = [sheet[r * 150 : (r + 1) * 150, c * 120 : (c + 1) * 120, :3] for r in range(2) for c in range(6)]
    assert all(_joint_coloured(c).sum() > 20 for c in cells)
    # the time label: dark text pixels in each cell's bottom-left corner
    assert all((c[-25:, :60].max(axis=2) < 80).sum() > 10 for c in cells)

    with pytest.raises(ParameterError, match="path: expected a .mp4 or .gif file name"):
        R.render_video(tmp_path / "a.avi", panels, fps=fps)
    with pytest.raises(ParameterError, match=r"panels\[0\]: expected \(positions, parents, caption\)"):
        R.render_video(tmp_path / "x.mp4", [pos[:10]], fps=fps)
