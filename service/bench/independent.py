"""Images posecell did not make: the printed target sheet imaged by a chain written with other tools.

posecell's renderer (:mod:`service.sim.render`) and its measurement share their authors, their
conventions and possibly their mistakes. Here the sheet posecell prints (``posecell targets sheet``,
:mod:`service.workflows.targets_sheet`) is imaged without any of posecell's image geometry:

1. **cairo** (CairoSVG) rasterises the SVG exactly as it would be printed: the disks, the ring
   sectors, the grey title, labels and ruler, anti-aliased, at ``RASTER_PX_PER_MM``;
2. **OpenCV** maps every pixel of the camera, ``OVERSAMPLE`` x ``OVERSAMPLE`` sub-pixels of it, to
   the sheet: ``cv2.undistortPointsIter`` through OpenCV's own lens model (``K``, ``k1 k2 p1 p2 k3``)
   to a ray, the ray onto the sheet's plane, ``cv2.remap`` (bilinear) from the raster; the
   sub-pixels are averaged (``cv2.INTER_AREA``): each pixel integrates the light over its area;
3. the light: the white print as retro-reflective sheeting under the ring light (``peak_dn`` on a
   ``background_dn`` plate, falling off towards the image corners), the optics' blur (a Gaussian),
   shot noise (Poisson, ``electrons_per_dn``) and read noise, quantised to 8 bits.

A cell's targets are seldom on one plane: the *corner* views image two sheets, the floor's and a
wall's standing at its far edge (:data:`CORNER`), each through the same chain, the nearer surface
hiding the farther per sub-pixel; its field gives each target's normal.

posecell then measures these frames with its defaults, the camera given as the Brown/Fraser model
fitted to OpenCV's (:func:`~service.core.geometry.opencv_compat.brown_from_opencv`, as a user of
an OpenCV calibration would), and the field as the sheet's field.json. The truth is the pose the
frame was made from. :func:`run` is ``posecell bench independent``.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from functools import lru_cache
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from service.bench.speed import path_poses, peer_measure
from service.core.geometry.frames import inv_T, pose_difference
from service.core.geometry.opencv_compat import brown_from_opencv
from service.core.results import PoseResult
from service.core.targets.field import Field
from service.pipeline.measure import FrameMeasurer
from service.sim.scene import reference_pose
from service.workflows.targets_sheet import SheetOptions, make_sheet

Array = NDArray[np.float64]
SHEET = SheetOptions()  # the default sheet: the reference scene's plate

RASTER_PX_PER_MM = 8.0  # the sheet's raster: ~7 raster pixels an image pixel at 1 m
OVERSAMPLE = 4  # sub-pixels a pixel side: the pixel's integration
MAP_STEP = 8  # sub-pixels between the exact ray computations; bilinear between (the map is smooth)
WIDTH, HEIGHT = 1300, 1030  # DESIGN section 7's camera, 6.7 um pixels, c = 12 mm
PIXEL_MM = 0.0067
K_OPENCV = np.array([[12.0 / PIXEL_MM, 0.0, 654.1], [0.0, 12.0 / PIXEL_MM, 511.2], [0.0, 0.0, 1.0]])
# a 12 mm lens on a 2/3" sensor, as OpenCV's calibrateCamera reports one: ~18 px of barrel distortion
# in the corners, a little decentring
DIST_OPENCV = np.array([-0.10, 0.05, 3.0e-4, -2.0e-4, 0.0])


@dataclass(frozen=True)
class Light:
    """How the print appears: DN of the plate and of the sheeting, the ring light's fall-off to the
    corners (a fraction), the optics' blur (px), shot noise (electrons a DN) and read noise (DN)."""

    background_dn: float = 12.0
    peak_dn: float = 220.0
    falloff: float = 0.3
    blur_px: float = 0.6
    electrons_per_dn: float = 8.0
    read_noise_dn: float = 1.5


@dataclass(frozen=True)
class SheetFrame:
    """One frame of the sheet: the 8-bit image, the pose it was made from and, per target of the
    field, its centre's projection (a point's, not the blob's centroid) through OpenCV's model and
    its disk's radius in the image (px, head-on at its depth)."""

    image: NDArray[np.uint8]
    T_field_camera: Array
    ids: list[str]
    uv_true: Array
    radius_px: Array
    meta: dict[str, Any] = field(default_factory=dict)


@lru_cache(maxsize=2)
def sheet(options: SheetOptions = SHEET) -> tuple[NDArray[np.float32], Field]:
    """The sheet rasterised by cairo (grey, 0..1, row 0 at the sheet's top edge) and its field."""
    import cairosvg  # only this bench needs it (the test extra)

    svg, field_ = make_sheet(options)
    w, h = round(options.width_mm * RASTER_PX_PER_MM), round(options.height_mm * RASTER_PX_PER_MM)
    png = cairosvg.svg2png(bytestring=svg.encode(), output_width=w, output_height=h)
    grey = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_GRAYSCALE)
    if grey is None or grey.shape != (h, w):
        raise RuntimeError(f"cairo gave no {w} x {h} raster of the sheet")
    return grey.astype(np.float32) / 255.0, field_


def _face_maps(T_camera_face: Array, options: SheetOptions) -> tuple[NDArray[np.float32], ...]:
    """Per camera sub-pixel, the raster's (column, row) that it sees on the sheet ``options`` lying in
    the x-y plane of the frame ``T_camera_face`` locates, for ``cv2.remap``, and the ray's distance to
    that plane (in units of its z): exact at the centre of every MAP_STEP x MAP_STEP block of
    sub-pixels, bilinear between (``cv2.resize`` puts its source samples there)."""
    q = OVERSAMPLE
    us = (np.arange(WIDTH * q // MAP_STEP) + 0.5) * MAP_STEP - 0.5
    vs = (np.arange(HEIGHT * q // MAP_STEP) + 0.5) * MAP_STEP - 0.5
    U, V = np.meshgrid(us, vs)
    # a sub-pixel's centre in the camera's pixels (the top-left pixel's centre is (0, 0))
    uv = np.stack([(U - (q - 1) / 2) / q, (V - (q - 1) / 2) / q], axis=-1).reshape(-1, 1, 2)
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-12)
    # the stubs do not admit None for R and P
    n = cv2.undistortPointsIter(uv, K_OPENCV, DIST_OPENCV, None, None, criteria).reshape(-1, 2)  # type: ignore[call-overload]
    # the ray (x, y, 1) of the camera onto the sheet's plane z = 0
    R, t = T_camera_face[:3, :3], T_camera_face[:3, 3]
    rays = np.concatenate([n, np.ones((len(n), 1))], axis=1) @ R  # each ray in the face's frame: R' ray
    origin = -R.T @ t
    s = -origin[2] / rays[:, 2]
    p = origin[None, :2] + s[:, None] * rays[:, :2]
    col = (p[:, 0] + options.width_mm / 2) * RASTER_PX_PER_MM - 0.5
    row = (options.height_mm / 2 - p[:, 1]) * RASTER_PX_PER_MM - 0.5
    size = (WIDTH * q, HEIGHT * q)
    return tuple(
        cv2.resize(a.reshape(U.shape).astype(np.float32), size, interpolation=cv2.INTER_LINEAR) for a in (col, row, s)
    )


Faces = tuple[tuple[SheetOptions, Array], ...]  # each sheet and T_field_face, the sheet in its x-y plane


def _radiance(T_camera_field: Array, faces: Faces) -> Array:
    """Per camera pixel, the mean over its sub-pixels of the print each one sees (0..1): of each sheet
    the nearest along the ray; a sheet seen from behind shows its dark back."""
    sub = np.zeros((HEIGHT * OVERSAMPLE, WIDTH * OVERSAMPLE), np.float32)
    nearest = np.full(sub.shape, np.inf, np.float32)
    for options, T_field_face in faces:
        raster, _ = sheet(options)
        T_camera_face = T_camera_field @ T_field_face
        map_col, map_row, dist = _face_maps(T_camera_face, options)
        rows, cols = raster.shape
        on = (dist > 0) & (dist < nearest) & (map_col > -0.5) & (map_col < cols - 0.5)
        on &= (map_row > -0.5) & (map_row < rows - 0.5)
        # its printed face (+z) towards the camera: the camera on the + side of its plane
        front = float(T_camera_face[:3, 2] @ -T_camera_face[:3, 3]) > 0
        seen = cv2.remap(raster, map_col, map_row, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0.0)
        sub[on] = seen[on] if front else 0.0
        nearest[on] = dist[on]
    return cv2.resize(sub, (WIDTH, HEIGHT), interpolation=cv2.INTER_AREA).astype(np.float64)


def image_of_sheet(
    T_field_camera: Array, light: Light, rng: np.random.Generator, options: SheetOptions = SHEET
) -> SheetFrame:
    """The sheet seen from ``T_field_camera`` (4, 4), mm, in the light ``light``."""
    return image_of_faces(T_field_camera, light, rng, ((options, np.eye(4)),), sheet(options)[1])


def image_of_faces(
    T_field_camera: Array, light: Light, rng: np.random.Generator, faces: Faces, field_: Field
) -> SheetFrame:
    """The sheets ``faces`` (whose targets ``field_`` lists) seen from ``T_field_camera`` (4, 4), mm."""
    T_camera_field = inv_T(T_field_camera)
    radiance = _radiance(T_camera_field, faces)
    v, u = np.mgrid[0:HEIGHT, 0:WIDTH]
    r2 = ((u - K_OPENCV[0, 2]) ** 2 + (v - K_OPENCV[1, 2]) ** 2) / (K_OPENCV[0, 2] ** 2 + K_OPENCV[1, 2] ** 2)
    signal = light.background_dn + (light.peak_dn - light.background_dn) * radiance * (1.0 - light.falloff * r2)
    if light.blur_px > 0:
        signal = cv2.GaussianBlur(signal, (0, 0), light.blur_px)
    electrons = rng.poisson(np.maximum(signal, 0.0) * light.electrons_per_dn)
    dn = electrons / light.electrons_per_dn + rng.normal(0.0, light.read_noise_dn, signal.shape)
    image = np.clip(np.rint(dn), 0, 255).astype(np.uint8)
    uv, _ = cv2.projectPoints(
        field_.xyz, cv2.Rodrigues(T_camera_field[:3, :3])[0], T_camera_field[:3, 3], K_OPENCV, DIST_OPENCV
    )
    depth_mm = field_.xyz @ T_camera_field[2, :3] + T_camera_field[2, 3]
    radius_px = 0.5 * field_.diameters_mm * K_OPENCV[0, 0] / depth_mm
    return SheetFrame(image, T_field_camera, list(field_.ids), uv.reshape(-1, 2), radius_px)


# A corner of a cell: the floor's sheet and a wall's (20 coded targets, codes 31-50, 80 uncoded)
# standing upright on the floor sheet's far edge (y = +300 mm), printed face towards -y
WALL = SheetOptions(
    width_mm=720.0, height_mm=420.0, n_coded=20, n_uncoded=80, first_code=31, name="wall", title="posecell wall"
)
_UPRIGHT = np.array([[1.0, 0.0, 0.0, 0.0], [0.0, 0.0, -1.0, 300.0], [0.0, 1.0, 0.0, WALL.height_mm / 2], [0, 0, 0, 1]])
CORNER: Faces = ((SHEET, np.eye(4)), (WALL, _UPRIGHT))


@lru_cache(maxsize=2)
def corner_field(with_normals: bool = True) -> Field:
    """The field of :data:`CORNER`: each sheet's targets in the field frame (the wall's uncoded ones
    renamed ``W<n>``), with each target's normal (``with_normals`` False: without, as a field on one
    plane would be given)."""
    ids: list[str] = []
    xyz, codes, diameters, normals = [], [], [], []
    for k, (options, T) in enumerate(CORNER):
        f = sheet(options)[1]
        ids += [i if k == 0 or i.startswith("C") else "W" + i[1:] for i in f.ids]
        xyz.append(f.xyz @ T[:3, :3].T + T[:3, 3])
        codes.append(f.codes)
        diameters.append(f.diameters_mm)
        normals.append(np.tile(T[:3, 2], (len(f), 1)))
    return Field(
        "corner",
        tuple(ids),
        np.vstack(xyz),
        np.concatenate(codes),
        np.concatenate(diameters),
        np.vstack(normals) if with_normals else None,
    )


@dataclass(frozen=True)
class View:
    """A row of the bench: the camera's view of the sheet and the light."""

    name: str
    view_deg: float
    distance_mm: float
    light: Light = Light()
    corner: bool = False  # the floor's and a wall's sheets (CORNER), looked at near their edge


VIEWS = (
    View("head-on, 1 m", 90.0, 1000.0),
    View("60 deg, 1 m", 60.0, 1000.0),
    View("45 deg, 1 m", 45.0, 1000.0),
    View("head-on, 0.7 m (part of the sheet)", 90.0, 700.0),
    View("60 deg, 1.4 m", 60.0, 1400.0),
    View("60 deg, 1 m, blur 1.2 px, read noise 4 DN", 60.0, 1000.0, Light(blur_px=1.2, read_noise_dn=4.0)),
    # the ring light's return at twice and four times full scale: most disks' tops clipped at 255
    View("60 deg, 1 m, overexposed 2x", 60.0, 1000.0, Light(peak_dn=2 * Light.peak_dn)),
    View("60 deg, 1 m, overexposed 4x", 60.0, 1000.0, Light(peak_dn=4 * Light.peak_dn)),
    View("corner: floor and wall, 60 deg, 1.3 m", 60.0, 1300.0, corner=True),
    # close: a coded target with its ring fills a 64 px noise tile (it was taken for 30x the noise)
    View("head-on, 0.5 m (coded targets 36 px across)", 90.0, 500.0),
    # the ring light's beam and the lens: the corners 60 % darker than the centre (by default 30 %);
    # with one edge level each disk's centre moved towards the light, the pose 1.6x further off
    View("60 deg, 1 m, corners 60 % darker", 60.0, 1000.0, Light(falloff=0.6)),
    # out of focus: the blur fills the gap between a coded target's disk and its ring (it gave no pose)
    View("60 deg, 1 m, out of focus (blur 2.5 px)", 60.0, 1000.0, Light(blur_px=2.5)),
    # grazing: a far coded target's disk joins its ring's near arc at the segmentation level (1-3 a
    # frame went unnamed until the full frame measured such targets in windows about the pose's prediction)
    View("grazing 30 deg, 1 m", 30.0, 1000.0),
)
CORNER_LOOK_MM = (0.0, 250.0, 60.0)  # where the corner views look: near the wall's foot


def frames_of(view: View, n: int, seed: int) -> list[SheetFrame]:
    """``n`` frames of ``view``: the camera rolled, turned and aimed a little differently each time."""
    rng = np.random.default_rng(seed)
    centre = CORNER_LOOK_MM if view.corner else (0.0, 0.0, 0.0)
    out = []
    for _ in range(n):
        look = (centre[0] + float(rng.uniform(-40, 40)), centre[1] + float(rng.uniform(-30, 30)), centre[2])
        T = reference_pose(
            view.view_deg,
            view.distance_mm * float(rng.uniform(0.97, 1.03)),
            roll_deg=float(rng.uniform(-20, 20)),
            azimuth_deg=float(rng.uniform(-30, 30)),
            look_at_mm=look,
        )
        out.append(_image(T, view.light, rng, view.corner))
    return out


def _image(T_field_camera: Array, light: Light, rng: np.random.Generator, corner: bool) -> SheetFrame:
    if corner:
        return image_of_faces(T_field_camera, light, rng, CORNER, corner_field())
    return image_of_sheet(T_field_camera, light, rng)


def path_frames(
    n: int, seed: int, view_deg: float = 60.0, light: Light = Light(), corner: bool = False
) -> list[SheetFrame]:
    """``n`` frames 4 ms apart along ``posecell bench speed``'s path (a robot at ~100 mm/s), views
    ``view_deg`` +- 10 deg: a sequence for ROI tracking (``corner``: of :data:`CORNER`, from 1.3 m)."""
    rng = np.random.default_rng(seed)
    poses = path_poses(n, view_deg, 1300.0, CORNER_LOOK_MM) if corner else path_poses(n, view_deg)
    return [_image(T, light, rng, corner) for T in poses]


@dataclass
class Score:
    """One tool's figures over a row's frames."""

    ms: list[float] = field(default_factory=list)
    pose_mm: list[float] = field(default_factory=list)
    pose_deg: list[float] = field(default_factory=list)
    centre_err: list[Array] = field(default_factory=list)
    found: int = 0
    visible: int = 0
    coded: int = 0
    wrong: int = 0
    failed: int = 0

    def merge(self, other: Score) -> None:
        """Add ``other``'s frames to these."""
        self.ms += other.ms
        self.pose_mm += other.pose_mm
        self.pose_deg += other.pose_deg
        self.centre_err += other.centre_err
        self.found += other.found
        self.visible += other.visible
        self.coded += other.coded
        self.wrong += other.wrong
        self.failed += other.failed


def _visible(frame: SheetFrame, margin_px: float = 12.0) -> NDArray[np.bool_]:
    """The targets whose centre is ``margin_px`` and whose disk (as large as head-on) 2 px clear of
    the image border."""
    uv = frame.uv_true
    margin_px = np.maximum(margin_px, frame.radius_px + 2.0)
    return (
        (uv[:, 0] > margin_px)
        & (uv[:, 0] < WIDTH - 1 - margin_px)
        & (uv[:, 1] > margin_px)
        & (uv[:, 1] < HEIGHT - 1 - margin_px)
    )


def measure_posecell(measurer: FrameMeasurer, frame: SheetFrame, score: Score, t_s: float | None = None) -> str:
    """posecell on ``frame`` (a full frame; with ``t_s``, tracked as the service tracks): its time,
    the pose's error and each target's centre against its true projection; a target named wrongly
    (> 1 px from its name's projection) counts. Returns the mode ("full" or "roi")."""
    truth = dict(zip(frame.ids, frame.uv_true, strict=True))
    score.visible += int(_visible(frame).sum())
    t0 = time.perf_counter()
    out = measurer.measure(frame.image, t_s=t_s)
    score.ms.append((time.perf_counter() - t0) * 1e3)
    if not isinstance(out.result, PoseResult):
        score.failed += 1
        return out.mode
    d_mm, d_deg = pose_difference(out.result.T_field_camera, frame.T_field_camera)
    score.pose_mm.append(d_mm)
    score.pose_deg.append(d_deg)
    for t in out.result.targets:
        e = np.asarray(t.uv) - truth[t.id]
        if np.hypot(*e) > 1.0:
            score.wrong += 1
            continue
        score.found += 1
        score.coded += t.id.startswith("C")
        score.centre_err.append(e)
    return out.mode


def measure_peer(field_: Field, frame: SheetFrame, score: Score) -> None:
    """The peer (``posecell bench speed``'s: threshold, labelling, centroids, ``solvePnP`` with the
    true OpenCV camera), given the identities (matched to the truth within 2 px, not timed)."""
    from scipy.spatial import cKDTree

    score.visible += int(_visible(frame).sum())
    t0 = time.perf_counter()
    uv = peer_measure(frame.image, K_OPENCV, DIST_OPENCV)
    t_detect = time.perf_counter()
    d, j = cKDTree(frame.uv_true).query(uv, distance_upper_bound=2.0)
    ok = np.isfinite(d)
    t_ident = time.perf_counter()
    if ok.sum() < 6:
        score.failed += 1
        return
    good, rvec, tvec = cv2.solvePnP(field_.xyz[j[ok]], uv[ok], K_OPENCV, DIST_OPENCV, flags=cv2.SOLVEPNP_ITERATIVE)
    score.ms.append(((t_detect - t0) + (time.perf_counter() - t_ident)) * 1e3)
    score.found += int(ok.sum())
    score.centre_err += list(uv[ok] - frame.uv_true[j[ok]])
    if not good:
        score.failed += 1
        return
    T_camera_field = np.eye(4)
    T_camera_field[:3, :3] = cv2.Rodrigues(rvec)[0]
    T_camera_field[:3, 3] = tvec.ravel()
    d_mm, d_deg = pose_difference(inv_T(T_camera_field), frame.T_field_camera)
    score.pose_mm.append(d_mm)
    score.pose_deg.append(d_deg)


def _med(x: list[float], fmt: str) -> str:
    return format(float(np.median(x)), fmt) if x else "—"


def _rms(e: list[Array]) -> str:
    return f"{float(np.sqrt(np.mean(np.square(e)))):.4f}" if e else "—"


def _tracking(fit_camera: Any, n: int, seed: int, corner: bool = False, light: Light = Light()) -> str:
    """A row of the ROI tracking table: a path of ``n`` frames, 4 ms apart, tracked by posecell as the
    service tracks it (the first frame in full) and measured by the peer frame by frame."""
    frames = path_frames(n, seed, light=light, corner=corner)
    field_ = corner_field() if corner else sheet()[1]
    tracker = FrameMeasurer(fit_camera, field_)
    tracker.measure(frames[0].image)  # warm-up: first calls allocate and fill caches
    tracker.reset()
    roi, full, peer = Score(), Score(), Score()
    for k, frame in enumerate(frames):
        if k % 2:  # who goes first alternates
            measure_peer(field_, frame, peer)
        # tracked frames go to the ROI score; the first (and any lost one) to the full frames'
        probe = Score()
        mode = measure_posecell(tracker, frame, probe, t_s=k * 0.004)
        (roi if mode == "roi" else full).merge(probe)
        if k % 2 == 0:
            measure_peer(field_, frame, peer)
    p99 = f"{float(np.percentile(roi.ms, 99)):.2f}" if roi.ms else "—"
    ratio = f"{np.median(peer.ms) / np.median(roi.ms):.2f}" if roi.ms and peer.ms else "—"
    name = "corner: floor and wall, 60 ± 10 deg, ~1.3 m" if corner else "60 ± 10 deg, ~1 m"
    if light.blur_px != Light.blur_px:
        name += f", out of focus (blur {light.blur_px:g} px)"
    return (
        f"| {name}, 4 ms apart | {n} | {len(roi.ms)} | {_med(roi.ms, '.3f')} | {p99} | "
        f"{roi.found} / {roi.visible} | {roi.coded} | {roi.wrong} | {_rms(roi.centre_err)} | "
        f"{_med(roi.pose_mm, '.4f')} | {roi.failed} | {_med(peer.ms, '.2f')} | {_med(peer.pose_mm, '.4f')} | {ratio} |"
    )


def run(n_frames: int = 5, seed: int = 1, tracked_frames: int | None = None) -> str:
    """The tables of ``posecell bench independent``: each row's frames measured by posecell (defaults,
    full frame) and by the peer, in turn; then paths of ``tracked_frames`` (by default ``6
    n_frames``) frames tracked (ROI)."""
    cv2.setNumThreads(1)
    n_tracked = 6 * n_frames if tracked_frames is None else tracked_frames
    fit = brown_from_opencv(K_OPENCV, DIST_OPENCV, WIDTH, HEIGHT, (PIXEL_MM, PIXEL_MM))
    measurers = {False: FrameMeasurer(fit.camera, sheet()[1]), True: FrameMeasurer(fit.camera, corner_field())}
    rows = [
        "| view | frames | targets named / whole in view | coded named | named wrongly | centre RMS px | "
        "pose error mm (median) | pose error deg (median) | failed | ms median | "
        "peer: found | peer centre RMS px | peer pose error mm | peer ms median |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for k, view in enumerate(VIEWS):
        frames = frames_of(view, n_frames, seed + k)
        measurer, field_ = measurers[view.corner], measurers[view.corner].field
        measurer.measure(frames[0].image)  # warm-up: first calls allocate and fill caches
        ours, peer = Score(), Score()
        for i, frame in enumerate(frames):  # who goes first alternates
            for who in ("ours", "peer") if i % 2 == 0 else ("peer", "ours"):
                if who == "ours":
                    measure_posecell(measurer, frame, ours)
                else:
                    measure_peer(field_, frame, peer)
        rows.append(
            f"| {view.name} | {len(frames)} | {ours.found} / {ours.visible} | {ours.coded} | {ours.wrong} | "
            f"{_rms(ours.centre_err)} | {_med(ours.pose_mm, '.4f')} | {_med(ours.pose_deg, '.5f')} | {ours.failed} | "
            f"{_med(ours.ms, '.2f')} | {peer.found} | {_rms(peer.centre_err)} | {_med(peer.pose_mm, '.4f')} | "
            f"{_med(peer.ms, '.2f')} |"
        )
    rows += [
        "",
        f"posecell's printed sheet ({len(sheet()[1])} targets) rasterised by cairo and imaged through OpenCV's "
        f"lens model (K, k1 k2 p1 p2 k3 = {', '.join(f'{d:g}' for d in DIST_OPENCV)}), {OVERSAMPLE}x"
        f"{OVERSAMPLE} sub-pixels a pixel, blur, shot and read noise (`service/bench/independent.py`); posecell "
        f"with its defaults and the Brown/Fraser model fitted to OpenCV's ({fit.rms_px:.4f} px RMS, "
        f"{fit.max_px:.4f} max), full frames; the peer with OpenCV's own model, given the identities. "
        "Centres against the true projections of the targets' centres (a point's, not a blob's: the "
        "perspective shift of a disk's image, < 0.01 px here, is in the figure); *whole in view*: the disk, "
        "as large as head-on, 2 px and its centre 12 px clear of the image border (a foreshortened one "
        "nearer is named too). "
        f"*Corner*: that sheet on the floor and a {WALL.width_mm:.0f} x {WALL.height_mm:.0f} mm sheet "
        f"({len(sheet(WALL)[1])} targets) standing on its far edge, the field giving each target's normal.",
        "",
        "ROI tracking on the same kind of images: a path like `posecell bench speed`'s, the frames 4 ms apart "
        "(250 Hz), posecell with its defaults (the first frame in full, then windows about the predicted "
        "targets), the peer measuring every frame in full:",
        "",
        "| sequence | frames | tracked | ROI ms median | ROI ms p99 | targets named / whole in view | coded named | "
        "named wrongly | centre RMS px | pose error mm (median) | failed | peer ms median | peer pose error mm | "
        "× peer speed |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
        _tracking(fit.camera, n_tracked, seed + 100),
        _tracking(fit.camera, n_tracked, seed + 200, corner=True),
        # the rim of an ROI window follows the last frame's blur (with a fixed 3 px rim: 78 % kept)
        _tracking(fit.camera, n_tracked, seed + 300, light=Light(blur_px=2.5)),
    ]
    return "\n".join(rows)
