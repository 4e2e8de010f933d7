"""Offscreen skeleton rendering with pyvista/VTK: frames, videos, contact sheets.

Bones are tubes, joints spheres, over a floor, seen by a fixed perspective
camera in front of the speaker (on +z, looking back at the body) framed from
the bounding box of the whole clip, so the body never leaves the view. One
VTK pipeline per panel is built once and only its points change per frame.

No display is needed: on Linux without ``DISPLAY`` the module selects VTK's
EGL render window (``VTK_DEFAULT_OPENGL_WINDOW``, read when the first window
is created); the VTK >= 9.4 PyPI wheel loads the system's libEGL at run time.
See ``docs/rendering.md`` for what the machine needs.

Coordinates: metres, y up, the speaker facing +z. Images are uint8 RGB
``(h, w, 3)``, row 0 at the top.

Length: over the package's 800-line mark on purpose. Frames, videos and contact
sheets share one VTK pipeline (:class:`SkeletonRenderer`), one camera fit and one
set of panel and caption checks; split in two, each half would import the
other's private helpers.
"""
from __future__ import annotations

import functools
import math
import os
import sys
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterator, Sequence

import numpy as np

from gesturedb.errors import GestureDBError, InputFileError, ParameterError

# VTK reads this when the first render window is created. Without it VTK first
# tries X11, fails with a warning and only then falls back to EGL.
if sys.platform.startswith("linux") and not os.environ.get("DISPLAY"):
    os.environ.setdefault("VTK_DEFAULT_OPENGL_WINDOW", "vtkEGLRenderWindow")

__all__ = [
    "Camera",
    "Style",
    "SkeletonRenderer",
    "fit_camera",
    "project_points",
    "render_frames",
    "render_video",
    "render_contact_sheet",
    "compose_panels",
]


@dataclass(frozen=True)
class Style:
    """Colours (RGB in [0, 1]) and sizes of a rendered skeleton.

    ``joint_radius_m`` / ``bone_radius_m`` of None scale with the clip's
    height (2.2 % and 1.1 % of it); a joint's sphere is also kept below 45 %
    of its shortest bone, so finger joints stay small.

    ``supersample`` = k renders k times larger and averages k x k blocks:
    anti-aliasing that costs about k^2 in render time (VTK's MSAA and FXAA
    cost more than that on the software rasteriser of a headless machine).
    """

    joint_color: tuple[float, float, float] = (0.93, 0.42, 0.10)
    bone_color: tuple[float, float, float] = (0.22, 0.42, 0.78)
    floor_color: tuple[float, float, float] = (0.86, 0.86, 0.84)
    background: tuple[float, float, float] = (0.97, 0.97, 0.97)
    text_color: tuple[int, int, int] = (20, 20, 20)
    joint_radius_m: float | None = None
    bone_radius_m: float | None = None
    floor: bool = True
    smooth: bool = True
    supersample: int = 1


@dataclass(frozen=True)
class Camera:
    """A pinhole camera with VTK's conventions.

    Attributes
    ----------
    position, focal_point, view_up : tuple of 3 floats, metres / direction
    view_angle_deg : float
        Vertical field of view in degrees.
    size : (width, height) in pixels
    floor_y : float
        Height of the floor plane (metres).
    floor_extent : (xmin, xmax, zmin, zmax), metres
    height_m : float
        Height of the framed motion's bounding box; sizes joints and bones.
    """

    position: tuple[float, float, float]
    focal_point: tuple[float, float, float]
    view_up: tuple[float, float, float]
    view_angle_deg: float
    size: tuple[int, int]
    floor_y: float = 0.0
    floor_extent: tuple[float, float, float, float] = (-1.0, 1.0, -1.0, 1.0)
    height_m: float = 1.7

    def axes(self) -> np.ndarray:
        """Rows: camera right, up and backward (away from the scene) unit vectors."""
        pos = np.asarray(self.position, dtype=np.float64)
        back = pos - np.asarray(self.focal_point, dtype=np.float64)
        back /= np.linalg.norm(back)
        right = np.cross(np.asarray(self.view_up, dtype=np.float64), back)
        right /= np.linalg.norm(right)
        up = np.cross(back, right)
        return np.stack([right, up, back])


def _as_positions(x: Any, name: str = "positions") -> np.ndarray:
    arr = np.asarray(x)
    if arr.ndim == 2 and arr.shape[1] == 3:
        arr = arr[None]
    if arr.ndim != 3 or arr.shape[2] != 3 or arr.shape[0] == 0 or arr.shape[1] == 0:
        raise ParameterError(f"{name}: expected joint positions of shape (F, J, 3); got shape {arr.shape}")
    if not np.issubdtype(arr.dtype, np.number):
        raise ParameterError(f"{name}: expected real numbers; got dtype {arr.dtype}")
    arr = arr.astype(np.float64, copy=False)
    if not np.all(np.isfinite(arr)):
        raise ParameterError(f"{name}: expected finite values; got NaN or inf")
    return arr


def _as_parents(parents: Any, n_joints: int) -> np.ndarray:
    p = np.asarray(parents)
    if p.shape != (n_joints,) or not np.issubdtype(p.dtype, np.integer):
        raise ParameterError(
            f"parents: expected {n_joints} integer parent indices (-1 for a root); got {p.dtype} shape {p.shape}"
        )
    bad = [(j, int(q)) for j, q in enumerate(p) if q < -1 or q >= n_joints or q == j]
    if bad:
        raise ParameterError(f"parents: expected -1 or another joint's index in [0, {n_joints}); got {bad[:5]}")
    return p.astype(np.int64)


def _as_size(size: Any) -> tuple[int, int]:
    try:
        w, h = (int(v) for v in size)
    except (TypeError, ValueError):
        raise ParameterError(f"size: expected (width, height) in pixels; got {size!r}") from None
    if w < 16 or h < 16 or w > 8192 or h > 8192:
        raise ParameterError(f"size: expected width and height in [16, 8192] pixels; got {size!r}")
    return w, h


# ------------------------------------------------------------------------- camera
def fit_camera(
    positions,
    *,
    size=(640, 480),
    view_angle_deg=30.0,
    facing=(0.0, 0.0, 1.0),
    elevation_deg=8.0,
    margin=1.12,
) -> Camera:
    """A camera in front of the speaker that keeps every frame in view.

    Parameters
    ----------
    positions : ndarray [shape=(F, J, 3)] or list of them, metres
        All motions that will be shown with this camera (side-by-side panels
        share one camera so they are framed identically).
    size : (width, height), pixels
    view_angle_deg : float
        Vertical field of view.
    facing : 3 floats
        Direction the speaker faces; the camera sits on that side. The
        project's data faces +z; pass a direction computed from the hips and
        shoulders for other data.
    elevation_deg : float
        Camera raised above the body's centre by this angle, to see the floor.
    margin : float
        Room around the bounding box: its corners project within
        1 / margin of the image half-width / half-height (1 = touching).

    Returns
    -------
    Camera
    """
    motions = positions if isinstance(positions, (list, tuple)) else [positions]
    pts = np.concatenate([_as_positions(m).reshape(-1, 3) for m in motions])
    w, h = _as_size(size)
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    extent = hi - lo
    height = max(float(extent[1]), 0.5)
    joint_r = 0.022 * height
    lo = lo - joint_r
    hi = hi + joint_r
    center = 0.5 * (lo + hi)
    f = np.asarray(facing, dtype=np.float64)
    f[1] = 0.0
    if not np.linalg.norm(f) > 1e-9:
        raise ParameterError(f"facing: expected a direction with a horizontal component; got {facing!r}")
    f /= np.linalg.norm(f)
    tan_v = math.tan(math.radians(view_angle_deg) / 2)
    tan_h = tan_v * w / h
    elev = math.radians(elevation_deg)
    direction = f * math.cos(elev) + np.array([0.0, 1.0, 0.0]) * math.sin(elev)
    # The camera looks along -direction at the box centre whatever its distance, so
    # its axes are known now. Perspective maps the box onto the convex hull of its
    # projected corners: fitting the 8 corners fits every point inside, exactly.
    axes = Camera((0.0, 0.0, 0.0), tuple(-direction), (0.0, 1.0, 0.0), view_angle_deg, (w, h)).axes()
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    cam = (corners - center) @ axes.T  # right, up, back(towards the camera)
    dist = float(np.max(cam[:, 2] + margin * np.maximum(np.abs(cam[:, 0]) / tan_h, np.abs(cam[:, 1]) / tan_v)))
    position = center + dist * direction
    floor_y = float(lo[1])
    pad = 0.3 * height
    return Camera(
        position=tuple(float(v) for v in position),
        focal_point=tuple(float(v) for v in center),
        view_up=(0.0, 1.0, 0.0),
        view_angle_deg=float(view_angle_deg),
        size=(w, h),
        floor_y=floor_y,
        floor_extent=(float(lo[0] - pad), float(hi[0] + pad), float(lo[2] - pad), float(hi[2] + pad)),
        height_m=height,
    )


def project_points(camera: Camera, points) -> np.ndarray:
    """World points to pixel coordinates with the camera's perspective projection.

    Same maths as VTK's camera (vertical view angle, aspect = width / height,
    display origin bottom-left), flipped so that row 0 is the top image row.

    Parameters
    ----------
    camera : Camera
    points : array_like [shape=(..., 3)], metres

    Returns
    -------
    ndarray [shape=(..., 2)], float64
        ``(column, row)`` in pixels; the pixel containing the point is
        ``image[int(row), int(column)]``. Points behind the camera are NaN.
    """
    p = np.asarray(points, dtype=np.float64)
    if p.shape[-1] != 3:
        raise ParameterError(f"points: expected shape (..., 3); got {p.shape}")
    w, h = camera.size
    rel = p - np.asarray(camera.position, dtype=np.float64)
    cam = rel @ camera.axes().T  # (..., 3): right, up, back
    depth = -cam[..., 2]
    tan_v = math.tan(math.radians(camera.view_angle_deg) / 2)
    with np.errstate(divide="ignore", invalid="ignore"):
        x_ndc = cam[..., 0] / depth / (tan_v * w / h)
        y_ndc = cam[..., 1] / depth / tan_v
    col = (x_ndc + 1.0) * 0.5 * w
    row = h - (y_ndc + 1.0) * 0.5 * h
    out = np.stack([col, row], axis=-1)
    out[depth <= 0] = np.nan
    return out


# ----------------------------------------------------------------------- renderer
def _joint_radii(parents: np.ndarray, rest: np.ndarray, base: float) -> np.ndarray:
    """Per-joint sphere radius: ``base``, but under 45 % of the shortest adjacent bone."""
    n = parents.shape[0]
    shortest = np.full(n, np.inf)
    for j, p in enumerate(parents):
        if p >= 0:
            length = float(np.linalg.norm(rest[j] - rest[p]))
            if length > 1e-6:
                shortest[j] = min(shortest[j], length)
                shortest[p] = min(shortest[p], length)
    return np.minimum(base, 0.45 * shortest)


class SkeletonRenderer:
    """One offscreen VTK scene for one skeleton; render poses into images.

    The scene (tubes, spheres, floor, lights, camera) is built once; each
    :meth:`render` only replaces the joint positions, which VTK propagates
    through the glyph and tube filters.

    Parameters
    ----------
    parents : ndarray [shape=(J,)], int
        Parent of each joint, -1 for a root.
    camera : Camera
    rest : ndarray [shape=(J, 3)], optional
        A representative pose; its bone lengths size the joint spheres
        (:func:`render_frames` passes the first frame). Without it every
        joint gets the full radius.
    style : Style, optional

    Use as a context manager or call :meth:`close` to free the GL context.
    """

    def __init__(self, parents, camera: Camera, *, rest=None, style: Style | None = None):
        import pyvista as pv
        from vtkmodules.vtkFiltersCore import vtkGlyph3D, vtkTubeFilter
        from vtkmodules.vtkFiltersSources import vtkSphereSource
        from vtkmodules.vtkRenderingCore import vtkActor, vtkPolyDataMapper

        pv.OFF_SCREEN = True
        self.style = style or Style()
        self.camera = camera
        p = np.asarray(parents)
        if p.ndim != 1:
            raise ParameterError(f"parents: expected a 1-D array of parent indices; got shape {p.shape}")
        self.parents = _as_parents(p, p.shape[0])
        n = self.parents.shape[0]
        rest = np.zeros((n, 3)) if rest is None else _as_positions(rest, "rest")[0]
        if rest.shape[0] != n:
            raise ParameterError(f"rest: expected {n} joints like parents; got {rest.shape[0]}")
        height = camera.height_m
        base_joint = self.style.joint_radius_m or 0.022 * height
        base_bone = self.style.bone_radius_m or 0.011 * height
        radii = _joint_radii(self.parents, rest, base_joint)
        w, h = camera.size
        k = int(self.style.supersample)
        if k < 1 or k > 4:
            raise ParameterError(f"style.supersample: expected an integer in 1..4; got {self.style.supersample!r}")
        self._k = k

        self._plotter = pv.Plotter(off_screen=True, window_size=(w * k, h * k), lighting="none")
        pl = self._plotter
        # No MSAA: on the software rasteriser of a headless machine it costs ~3x the frame.
        # Set before the first render, when the GL context is created.
        pl.ren_win.SetMultiSamples(0)
        pl.set_background(self.style.background)

        self._joints = pv.PolyData(rest.copy())
        self._joints.point_data["radius"] = radii
        self._joints.point_data.active_scalars_name = "radius"
        sphere = vtkSphereSource()
        sphere.SetRadius(1.0)
        sphere.SetThetaResolution(20)
        sphere.SetPhiResolution(14)
        glyph = vtkGlyph3D()
        glyph.SetInputData(self._joints)
        glyph.SetSourceConnection(sphere.GetOutputPort())
        glyph.SetScaleModeToScaleByScalar()
        glyph.SetScaleFactor(1.0)
        glyph.OrientOff()
        self._add(glyph, self.style.joint_color, vtkPolyDataMapper, vtkActor)

        bones = [(int(q), j) for j, q in enumerate(self.parents) if q >= 0]
        self._bones = None
        if bones:
            lines = np.array([[2, q, j] for q, j in bones], dtype=np.int64).ravel()
            self._bones = pv.PolyData(rest.copy(), lines=lines)
            # Tubes as thick as the thinner joint they connect, so finger bones stay thin.
            self._bones.point_data["radius"] = np.minimum(base_bone, 0.5 * radii)
            self._bones.point_data.active_scalars_name = "radius"
            tube = vtkTubeFilter()
            tube.SetInputData(self._bones)
            tube.SetNumberOfSides(14)
            tube.SetVaryRadiusToVaryRadiusByAbsoluteScalar()
            tube.CappingOn()
            self._add(tube, self.style.bone_color, vtkPolyDataMapper, vtkActor)

        if self.style.floor:
            x0, x1, z0, z1 = camera.floor_extent
            floor = pv.Plane(
                center=((x0 + x1) / 2, camera.floor_y, (z0 + z1) / 2),
                direction=(0, 1, 0),
                i_size=x1 - x0,
                j_size=z1 - z0,
            )
            pl.add_mesh(floor, color=self.style.floor_color, ambient=0.75, diffuse=0.35, specular=0.0)

        # Fixed scene lights (not camera lights): identical shading in every panel and frame.
        key = pv.Light(position=(2.0, 4.0, 4.0), focal_point=(0, 1, 0), intensity=0.75, light_type="scene light")
        fill = pv.Light(position=(-3.0, 2.0, 3.0), focal_point=(0, 1, 0), intensity=0.35, light_type="scene light")
        back = pv.Light(position=(0.0, 3.0, -4.0), focal_point=(0, 1, 0), intensity=0.2, light_type="scene light")
        for light in (key, fill, back):
            pl.add_light(light)

        cam = pl.camera
        cam.position = camera.position
        cam.focal_point = camera.focal_point
        cam.up = camera.view_up
        cam.view_angle = camera.view_angle_deg
        self._clip_range()
        self._closed = False

    def _add(self, algorithm, color, mapper_cls, actor_cls):
        mapper = mapper_cls()
        mapper.SetInputConnection(algorithm.GetOutputPort())
        mapper.ScalarVisibilityOff()
        actor = actor_cls()
        actor.SetMapper(mapper)
        prop = actor.GetProperty()
        prop.SetColor(*color)
        prop.SetAmbient(0.30)
        prop.SetDiffuse(0.75)
        prop.SetSpecular(0.15)
        prop.SetSpecularPower(20)
        if self.style.smooth:
            prop.SetInterpolationToPhong()
        self._plotter.add_actor(actor, reset_camera=False)

    def _clip_range(self):
        # Generous fixed near/far planes: the camera never moves, and
        # ResetCameraClippingRange per frame would cost time for nothing.
        d = float(np.linalg.norm(np.subtract(self.camera.position, self.camera.focal_point)))
        self._plotter.camera.clipping_range = (max(0.05, 0.1 * d), 10.0 * d + 20.0)

    @property
    def size(self) -> tuple[int, int]:
        return self.camera.size

    def display_points(self, points) -> np.ndarray:
        """Pixel coordinates of world points by VTK's own camera transform.

        The same convention as :func:`project_points` (column, row from the
        top); an independent path to check it against.

        Parameters
        ----------
        points : array_like [shape=(n, 3)], metres

        Returns
        -------
        ndarray [shape=(n, 2)]
        """
        ren = self._plotter.renderer
        h = self.camera.size[1]
        out = []
        for p in np.asarray(points, dtype=np.float64).reshape(-1, 3):
            ren.SetWorldPoint(float(p[0]), float(p[1]), float(p[2]), 1.0)
            ren.WorldToDisplay()
            x, y, _ = ren.GetDisplayPoint()
            # the window is supersample times the output size
            out.append((x / self._k, h - y / self._k))
        return np.asarray(out)

    def render(self, pose) -> np.ndarray:
        """Render one pose.

        Parameters
        ----------
        pose : ndarray [shape=(J, 3)], metres

        Returns
        -------
        ndarray [shape=(h, w, 3)], uint8
        """
        if self._closed:
            raise GestureDBError("SkeletonRenderer: render() after close()")
        pose = np.asarray(pose, dtype=np.float64)
        if pose.shape != (self.parents.shape[0], 3):
            raise ParameterError(f"pose: expected shape ({self.parents.shape[0]}, 3); got {pose.shape}")
        self._joints.points[:] = pose
        self._joints.Modified()
        if self._bones is not None:
            self._bones.points[:] = pose
            self._bones.Modified()
        self._plotter.render()
        img = self._plotter.screenshot(return_img=True)[..., :3]
        if self._k > 1:
            h, w = self.camera.size[1], self.camera.size[0]
            k = self._k
            img = img.reshape(h, k, w, k, 3).mean(axis=(1, 3)).round()
        return np.ascontiguousarray(img, dtype=np.uint8)

    def close(self) -> None:
        if not self._closed:
            self._plotter.close()
            self._closed = True

    def __enter__(self) -> "SkeletonRenderer":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def _frame_indices(n_frames: int, frames) -> np.ndarray:
    if frames is None:
        return np.arange(n_frames)
    idx = np.asarray(frames)
    if idx.ndim == 0:
        idx = idx.reshape(1)
    if idx.ndim != 1 or not np.issubdtype(idx.dtype, np.integer):
        raise ParameterError(f"frames: expected a 1-D sequence of frame indices; got {frames!r}")
    if idx.size and (idx.min() < 0 or idx.max() >= n_frames):
        raise ParameterError(f"frames: expected indices in [0, {n_frames}); got min {idx.min()}, max {idx.max()}")
    return idx


def render_frames(positions, parents, *, size=(640, 480), frames=None, camera=None, style=None) -> np.ndarray:
    """Render a motion as images.

    Parameters
    ----------
    positions : ndarray [shape=(F, J, 3)], metres
    parents : ndarray [shape=(J,)], int
        Parent index of each joint, -1 for a root.
    size : (width, height), pixels
    frames : sequence of int, optional
        Frames to render (default all).
    camera : Camera, optional
        Default: :func:`fit_camera` on the whole motion.
    style : Style, optional

    Returns
    -------
    ndarray [shape=(n, h, w, 3)], uint8
    """
    pos = _as_positions(positions)
    parents = _as_parents(parents, pos.shape[1])
    idx = _frame_indices(pos.shape[0], frames)
    cam = camera or fit_camera(pos, size=size)
    w, h = cam.size
    out = np.empty((idx.size, h, w, 3), dtype=np.uint8)
    with SkeletonRenderer(parents, cam, rest=pos[0], style=style) as r:
        for k, f in enumerate(idx):
            out[k] = r.render(pos[f])
    return out


# ------------------------------------------------------------------------ text
@functools.lru_cache(maxsize=16)
def _font(px: int):
    from PIL import ImageFont

    return ImageFont.load_default(size=px)


def _draw_text(img: np.ndarray, text: str, *, xy, px: int, color, anchor="la", box=True) -> np.ndarray:
    """Draw text onto an RGB uint8 image (PIL's bundled font); returns a new array."""
    from PIL import Image, ImageDraw

    im = Image.fromarray(img)
    d = ImageDraw.Draw(im)
    font = _font(px)
    if box:
        x0, y0, x1, y1 = d.textbbox(xy, text, font=font, anchor=anchor)
        d.rectangle((x0 - 4, y0 - 3, x1 + 4, y1 + 3), fill=(255, 255, 255))
    d.text(xy, text, font=font, fill=tuple(int(c) for c in color), anchor=anchor)
    return np.asarray(im)


def compose_panels(images: Sequence[np.ndarray], captions: Sequence[str | None] = (), *, style=None) -> np.ndarray:
    """Place panel images side by side, each with its caption at the top.

    Parameters
    ----------
    images : list of ndarray [shape=(h, w_i, 3)], uint8
        Same height.
    captions : list of str or None

    Returns
    -------
    ndarray [shape=(h, sum w_i, 3)], uint8
    """
    style = style or Style()
    out = []
    for k, img in enumerate(images):
        cap = captions[k] if k < len(captions) else None
        if cap:
            px = max(12, img.shape[0] // 22)
            img = _draw_text(img, str(cap), xy=(img.shape[1] // 2, 6), px=px, color=style.text_color, anchor="ma")
        if k < len(images) - 1:
            # A thin grey line between panels (drawn over the panel, so sizes add up).
            img = img.copy()
            img[:, -1] = 150
        out.append(img)
    return np.concatenate(out, axis=1) if len(out) > 1 else out[0]


# --------------------------------------------------------------------- panels
def _check_panels(panels) -> list[tuple[np.ndarray, np.ndarray, str | None]]:
    if not isinstance(panels, (list, tuple)) or not panels:
        raise ParameterError("panels: expected a non-empty list of (positions, parents, caption)")
    out = []
    for k, p in enumerate(panels):
        if not isinstance(p, (list, tuple)) or len(p) not in (2, 3):
            raise ParameterError(f"panels[{k}]: expected (positions, parents, caption); got {type(p).__name__}")
        pos = _as_positions(p[0], f"panels[{k}] positions")
        par = _as_parents(p[1], pos.shape[1])
        cap = p[2] if len(p) == 3 else None
        out.append((pos, par, None if cap is None else str(cap)))
    return out


def _timed_captions(captions) -> list[tuple[float, float, str]]:
    """Subtitles as (start_s, end_s, text); accepts a list of triples or a Words-like object."""
    if captions is None:
        return []
    if hasattr(captions, "start_s") and hasattr(captions, "end_s") and hasattr(captions, "text"):
        return [(float(a), float(b), str(t)) for a, b, t in zip(captions.start_s, captions.end_s, captions.text)]
    out = []
    for k, c in enumerate(captions):
        try:
            a, b, t = c
            out.append((float(a), float(b), str(t)))
        except (TypeError, ValueError):
            raise ParameterError(f"captions[{k}]: expected (start_s, end_s, text); got {c!r}") from None
    return out


def _subtitle_at(subs: list[tuple[float, float, str]], t: float, span_s: float = 2.0) -> str:
    """The words spoken around time t: the current word plus its neighbours within span_s."""
    current = [s for s in subs if s[0] <= t < s[1]]
    if not current:
        return ""
    near = [s for s in subs if s[1] > t - span_s / 2 and s[0] < t + span_s / 2]
    return " ".join(s[2] for s in near)


class _PanelSet:
    """Renderers for all panels with one shared camera; yields composed frames."""

    def __init__(self, panels, size, style, camera=None):
        self.panels = _check_panels(panels)
        self.style = style or Style()
        self.camera = camera or fit_camera([p[0] for p in self.panels], size=size)
        self.n_frames = max(p[0].shape[0] for p in self.panels)
        self.renderers = []
        try:
            for pos, par, _ in self.panels:
                self.renderers.append(SkeletonRenderer(par, self.camera, rest=pos[0], style=self.style))
        except Exception:
            self.close()
            raise

    def panel_images(self, f: int) -> list[np.ndarray]:
        # A panel shorter than the longest one holds its last pose.
        return [r.render(pos[min(f, pos.shape[0] - 1)]) for r, (pos, _, _) in zip(self.renderers, self.panels)]

    def frame(self, f: int) -> np.ndarray:
        return compose_panels(self.panel_images(f), [p[2] for p in self.panels], style=self.style)

    def close(self):
        for r in self.renderers:
            r.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


def _even(img: np.ndarray) -> np.ndarray:
    """Pad to even width/height with the background: H.264 yuv420p needs even sizes."""
    h, w = img.shape[:2]
    ph, pw = h % 2, w % 2
    if ph or pw:
        img = np.pad(img, ((0, ph), (0, pw), (0, 0)), mode="edge")
    return img


# ------------------------------------------------------------------------ audio
def _load_audio(audio, sr) -> tuple[np.ndarray, int]:
    if isinstance(audio, (str, os.PathLike)):
        import soundfile as sf

        try:
            y, file_sr = sf.read(os.fspath(audio), dtype="float32", always_2d=True)
        except Exception as e:  # soundfile raises several types for unreadable files
            raise InputFileError(audio, f"audio: expected a readable sound file; got {e}") from None
        return y.mean(axis=1), int(file_sr)
    if isinstance(audio, tuple) and len(audio) == 2:
        audio, sr = audio
    y = np.asarray(audio)
    if y.ndim == 2:
        y = y.mean(axis=1)
    if y.ndim != 1 or y.size == 0 or not np.issubdtype(y.dtype, np.floating):
        raise ParameterError(
            f"audio: expected a path, a 1-D float waveform or (waveform, sr); got dtype {y.dtype} shape {y.shape}"
        )
    if sr is None or not (int(sr) > 0):
        raise ParameterError(f"sr: expected the sample rate (Hz) of the audio array; got {sr!r}")
    return y.astype(np.float32, copy=False), int(sr)


def _fit_audio_length(y: np.ndarray, sr: int, duration_s: float) -> np.ndarray:
    """Trim, or pad with silence, to exactly the video's duration."""
    n = int(round(duration_s * sr))
    if y.shape[0] >= n:
        return y[:n]
    return np.concatenate([y, np.zeros(n - y.shape[0], dtype=y.dtype)])


# ------------------------------------------------------------------------ video
def render_video(
    path,
    panels,
    *,
    fps,
    audio=None,
    sr=None,
    captions=None,
    size=(640, 480),
    style=None,
    camera=None,
    quality=7,
    time_label=True,
):
    """Render side-by-side panels to an MP4 (H.264, with speech) or a GIF.

    Parameters
    ----------
    path : str or os.PathLike
        ``.mp4`` (H.264 + AAC through imageio-ffmpeg's bundled ffmpeg) or ``.gif``.
    panels : list of (positions, parents, caption)
        ``positions`` ndarray [shape=(F_i, J_i, 3)] metres, ``parents`` (J_i,),
        ``caption`` str or None drawn at the top of the panel. All panels share
        one camera; the video has ``max F_i`` frames, shorter panels hold
        their last pose.
    fps : float
        Frame rate of the motions and the video.
    audio : str, os.PathLike, ndarray or (ndarray, sr), optional
        Speech to mux into the MP4, trimmed or padded with silence to the
        video's duration. Ignored for GIF.
    sr : int, optional
        Sample rate when ``audio`` is an array.
    captions : list of (start_s, end_s, text) or Words, optional
        Timed subtitles (e.g. the transcript) drawn at the bottom.
    size : (width, height)
        Size of each panel in pixels.
    style : Style, optional
    camera : Camera, optional
        Default: fitted to all panels.
    quality : int
        0-10, imageio-ffmpeg's scale (7 -> x264 CRF 15).
    time_label : bool
        Draw the time in seconds in the bottom-left corner.

    Returns
    -------
    pathlib.Path
        The written file.
    """
    import imageio_ffmpeg

    path = Path(path)
    ext = path.suffix.lower()
    if ext not in (".mp4", ".gif"):
        raise ParameterError(f"path: expected a .mp4 or .gif file name; got {str(path)!r}")
    fps = float(fps)
    if not (fps > 0):
        raise ParameterError(f"fps: expected a positive frame rate; got {fps!r}")
    subs = _timed_captions(captions)
    style = style or Style()
    if not path.parent.exists():
        raise ParameterError(f"path: folder {str(path.parent)!r} does not exist")

    with _PanelSet(panels, size, style, camera) as ps:
        n = ps.n_frames

        def frames() -> Iterator[np.ndarray]:
            for f in range(n):
                img = ps.frame(f)
                t = f / fps
                px = max(12, img.shape[0] // 24)
                if time_label:
                    img = _draw_text(img, f"{t:6.2f} s", xy=(8, img.shape[0] - 8), px=px, color=style.text_color, anchor="lb")
                sub = _subtitle_at(subs, t)
                if sub:
                    img = _draw_text(
                        img, sub, xy=(img.shape[1] // 2, img.shape[0] - 8), px=px, color=style.text_color, anchor="mb"
                    )
                yield _even(img)

        if ext == ".gif":
            import imageio.v3 as iio

            # GIF delays are whole 1/100 s: Pillow stores 33.3 ms as 30 ms (30 fps plays at 33.3).
            with iio.imopen(path, "w", plugin="pillow") as wr:
                for img in frames():
                    wr.write(img, duration=1000.0 / fps, loop=0)
            return path

        wav = None
        try:
            if audio is not None:
                y, a_sr = _load_audio(audio, sr)
                y = _fit_audio_length(y, a_sr, n / fps)
                import soundfile as sf

                fd, wav = tempfile.mkstemp(suffix=".wav", dir=path.parent)
                os.close(fd)
                sf.write(wav, y, a_sr, subtype="PCM_16")
            gen = None
            for img in frames():
                if gen is None:
                    h, w = img.shape[:2]
                    gen = imageio_ffmpeg.write_frames(
                        str(path),
                        (w, h),
                        fps=fps,
                        codec="libx264",
                        pix_fmt_out="yuv420p",
                        quality=quality,
                        macro_block_size=2,
                        audio_path=wav,
                        audio_codec="aac" if wav else None,
                        output_params=["-movflags", "+faststart"],
                        ffmpeg_log_level="error",
                    )
                    gen.send(None)
                gen.send(np.ascontiguousarray(img).tobytes())
            gen.close()
        finally:
            if wav is not None and os.path.exists(wav):
                os.remove(wav)
    return path


def render_contact_sheet(path, panels, *, n=8, fps=30.0, size=(320, 360), style=None, camera=None):
    """A PNG grid of evenly spaced frames: one row per panel, time labels on each cell.

    Parameters
    ----------
    path : str or os.PathLike
        Output ``.png``.
    panels : list of (positions, parents, caption)
        As in :func:`render_video`; the caption starts each row.
    n : int
        Frames per row, evenly spaced from the first to the last frame of the
        longest panel (``round(linspace(0, F - 1, n))``).
    fps : float
        Frame rate, for the time labels.
    size : (width, height)
        Size of each cell in pixels.

    Returns
    -------
    pathlib.Path
    """
    import imageio.v3 as iio

    path = Path(path)
    if path.suffix.lower() != ".png":
        raise ParameterError(f"path: expected a .png file name; got {str(path)!r}")
    if not isinstance(n, (int, np.integer)) or n < 1:
        raise ParameterError(f"n: expected a positive number of frames; got {n!r}")
    fps = float(fps)
    if not (fps > 0):
        raise ParameterError(f"fps: expected a positive frame rate; got {fps!r}")
    style = style or Style()
    with _PanelSet(panels, size, style, camera) as ps:
        idx = np.unique(np.round(np.linspace(0, ps.n_frames - 1, n)).astype(int))
        rows = [[] for _ in ps.panels]
        for f in idx:
            for k, img in enumerate(ps.panel_images(int(f))):
                px = max(11, img.shape[0] // 20)
                img = _draw_text(img, f"{f / fps:.2f} s", xy=(6, img.shape[0] - 6), px=px, color=style.text_color, anchor="lb")
                if f == idx[0] and ps.panels[k][2]:
                    img = _draw_text(img, ps.panels[k][2], xy=(6, 6), px=px, color=style.text_color, anchor="la")
                # A thin separator keeps neighbouring cells apart.
                img = img.copy()
                img[:, -1] = 160
                img[-1, :] = 160
                rows[k].append(img)
        sheet = np.concatenate([np.concatenate(r, axis=1) for r in rows], axis=0)
    iio.imwrite(path, sheet)
    return path


def render_file(path, panels, *, fps, audio=None, sr=None, captions=None, **kwargs):
    """Render panels to whatever ``path`` names: ``.mp4`` / ``.gif`` video or a ``.png`` contact sheet.

    Parameters are those of :func:`render_video`; for ``.png`` only ``panels``
    and ``fps`` are used (plus ``n``, the number of frames, in ``kwargs``).
    """
    ext = os.path.splitext(os.fspath(path))[1].lower()
    if ext in (".mp4", ".gif"):
        return render_video(path, panels, fps=fps, audio=audio, sr=sr, captions=captions, **kwargs)
    if ext == ".png":
        return render_contact_sheet(path, panels, fps=fps, n=kwargs.get("n", 8))
    raise ParameterError(f"render output {os.fspath(path)!r}: expected a .mp4, .gif or .png file name, got {ext or 'no extension'!r}")
