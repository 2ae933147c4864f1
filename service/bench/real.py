"""``posecell bench real``: real images we did not make — MicMac's coded panel — as they are and
degraded as other hardware would give them, posecell beside the OpenCV peer in one run.

The data set (``../shared/data/micmac-circ-code-target``: 20 flash-lit 2000 x 1333 8-bit images of
a carbon panel with 73 AICON 14-bit coded targets and 166 dots) has no ground truth, so each row
compares poses with the pose posecell gives the image as it is: a degradation that changes the
pose shows as a difference. The camera is ``--camera`` (a camera.json of the panel's lens), or
posecell calibrates it from the 20 images first (``posecell calibrate camera`` with the code
family and the lens's nominal c and pixel size only, ~1-3 min), as a user would.

Rows: the images as they are, then :data:`DEGRADATIONS` (read noise, defocus, half the light, a
gradient, a hot spot, the smear of a camera moving during the exposure, and the 12-bit frame a
Mono12 camera would deliver). Per row: the images
that gave a pose; posecell's full-frame time (median, p99) with the default settings (the code
family given; ``bit_depth`` 12 for the 12-bit row); the targets named; the pose's difference from
the image's own (median and largest); and the same for the peer of ``posecell bench speed``
(threshold, connected components, ``solvePnP``), given the identities (each centroid within 2 px
of a target posecell named in the image as it is) and the threshold (40 DN, above the carbon
weave; 640 in the 12-bit row). posecell and the peer take the images in turn, in ``passes``
passes, so the host's drift slows both alike.
"""

from __future__ import annotations

import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from service.bench.speed import PEER_LABELLING
from service.core.geometry.frames import inv_T, pose_difference
from service.core.geometry.opencv_compat import opencv_from_brown
from service.core.results import PoseResult
from service.pipeline.measure import FrameMeasurer, MeasureSettings
from service.sim.render import smear
from service.store import formats

DEFAULT_DATA = Path(__file__).resolve().parents[3] / "shared" / "data" / "micmac-circ-code-target"
POSITIONS = "Positions-3D-14bit_lookup.txt"
C_MM, PIXEL_MM = 24.0, 23.5 / 6000 * 3  # Nikon D5600 with a 24 mm lens, the images scaled down 3x
PEER_THRESHOLD_DN = 40.0  # above the carbon weave's specks, below the dimmest targets (~50 DN)
PASSES = 3

Degrade = Callable[[NDArray[np.uint8], np.random.Generator], NDArray[Any]]


def _noise(img: NDArray[np.uint8], rng: np.random.Generator) -> NDArray[Any]:
    return np.clip(img + rng.normal(0.0, 4.0, img.shape), 0, 255).round().astype(np.uint8)


def _gradient(img: NDArray[np.uint8], rng: np.random.Generator) -> NDArray[Any]:
    h, w = img.shape
    ramp = np.linspace(0.0, 40.0, w)[None, :] + np.linspace(0.0, 20.0, h)[:, None]
    return np.clip(img + ramp, 0, 255).astype(np.uint8)


def _hot_spot(img: NDArray[np.uint8], rng: np.random.Generator) -> NDArray[Any]:
    v, u = np.mgrid[: img.shape[0], : img.shape[1]]
    spot = 60.0 * np.exp(-((u - 900.0) ** 2 + (v - 600.0) ** 2) / (2 * 300.0**2))
    return np.clip(img + spot, 0, 255).astype(np.uint8)


def _twelve_bit(img: NDArray[np.uint8], rng: np.random.Generator) -> NDArray[Any]:
    # a Mono12 camera's frame: uint16 up to 4095, its low four bits noise
    return (img.astype(np.uint16) << 4) + rng.integers(0, 16, img.shape).astype(np.uint16)


#: (row, image -> image): the panel as another camera or light would give it
DEGRADATIONS: tuple[tuple[str, Degrade], ...] = (
    ("read noise 4 DN", _noise),
    ("defocus 1 px", lambda img, rng: cv2.GaussianBlur(img, (0, 0), 1.0)),
    ("half the light", lambda img, rng: (img * 0.5 + 0.5).astype(np.uint8)),
    ("gradient 0-60 DN", _gradient),
    ("hot spot 60 DN", _hot_spot),
    ("motion blur 6 px", lambda img, rng: smear(img, 6.0, 30.0)),
    ("12 bit (Mono12)", _twelve_bit),
)


def calibrated_camera(data: Path, out: Path) -> Path:
    """``posecell calibrate camera`` on the data set's images with default detection: camera.json."""
    from service.workflows.calibrate_camera import MeasureOptions, run_camera_calibration

    run_camera_calibration(
        str(data / POSITIONS),
        output=str(out),
        images=[str(data / "images")],
        c_mm=C_MM,
        pixel_size_mm=PIXEL_MM,
        measure=MeasureOptions(code_family="aicon14"),
    )
    return out


def _peer(image: NDArray[Any], ids_uv: tuple[list[str], NDArray[np.float64]], xyz: Any, fit: Any, thr: float) -> Any:
    """The peer's pose (T_field_camera) or None, and its time, s (the identities' matching not timed)."""
    from scipy.spatial import cKDTree

    t0 = time.perf_counter()
    _, mask = cv2.threshold(image, thr, 255, cv2.THRESH_BINARY)
    mask = mask.astype(np.uint8)
    _, _, stats, centroids = cv2.connectedComponentsWithStatsWithAlgorithm(mask, 8, cv2.CV_32S, PEER_LABELLING)
    keep = (stats[1:, cv2.CC_STAT_AREA] >= 6) & (stats[1:, cv2.CC_STAT_AREA] < 5000)
    uv = centroids[1:][keep]
    t_detect = time.perf_counter() - t0
    ids, ref_uv = ids_uv
    d, j = cKDTree(ref_uv).query(uv, distance_upper_bound=2.0)
    ok = np.isfinite(d)
    if ok.sum() < 6:
        return None, t_detect
    t1 = time.perf_counter()
    found, rvec, tvec = cv2.solvePnP(xyz(ids, j[ok]), uv[ok], fit.K, fit.dist, flags=cv2.SOLVEPNP_ITERATIVE)
    t_pose = time.perf_counter() - t1
    if not found:
        return None, t_detect + t_pose
    T_camera_field = np.eye(4)
    T_camera_field[:3, :3] = cv2.Rodrigues(rvec)[0]
    T_camera_field[:3, 3] = tvec.ravel()
    return inv_T(T_camera_field), t_detect + t_pose


def _q(x: list[float], q: float) -> float:
    return float(np.quantile(x, q)) if x else float("nan")


def run(data: Path | None = None, camera: Path | None = None, passes: int = PASSES, every: int = 1) -> str:
    """The section's table (see the module docstring); ``every``: every n-th image only."""
    data = Path(data) if data is not None else DEFAULT_DATA
    if not (data / POSITIONS).exists():
        return f"_real: the MicMac panel data set is not at {data} (`--data`); section left out._"
    cv2.setNumThreads(1)
    field = formats.read_field(data / POSITIONS)
    paths = sorted((data / "images").glob("*_Scaled.tif"))[::every]
    said = []
    with tempfile.TemporaryDirectory() as tmp:
        if camera is None:
            t0 = time.perf_counter()
            camera = calibrated_camera(data, Path(tmp) / "camera.json")
            said.append(f"camera calibrated by posecell from the 20 images in {time.perf_counter() - t0:.0f} s")
        cam = formats.read_camera(camera)
    fit = opencv_from_brown(cam)
    plain = MeasureSettings.from_options(code_family="aicon14", roi_tracking=False)
    deep = MeasureSettings.from_options(code_family="aicon14", roi_tracking=False, bit_depth=12)
    measurer = {
        np.dtype(np.uint8): FrameMeasurer(cam, field, plain),
        np.dtype(np.uint16): FrameMeasurer(cam, field, deep),
    }
    images = [formats.read_image(p) for p in paths]
    reference: list[PoseResult | None] = []
    for img in images:
        r = measurer[img.dtype].measure(img).result
        reference.append(r if isinstance(r, PoseResult) else None)

    def xyz(ids: list[str], j: NDArray[np.intp]) -> Any:
        return field.xyz[field.indices_of([ids[k] for k in j])]

    rows = [("as they are", None), *DEGRADATIONS]
    lines = [
        "| images | posed | ms median | ms p99 | targets named (median) | Δ pose mm median / max | Δ pose ° max "
        "| peer posed | peer ms median | peer Δ pose mm median / max | × peer speed |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    rng = np.random.default_rng(7)
    for name, degrade in rows:
        shown = [img if degrade is None else degrade(img.copy(), rng) for img in images]
        ms: list[float] = []
        peer_ms: list[float] = []
        named: list[int] = []
        d_mm: dict[int, float] = {}
        d_deg: dict[int, float] = {}
        peer_d: dict[int, float] = {}
        for p in range(passes):
            for k, img in enumerate(shown):
                ref = reference[k]
                for who in ("ours", "peer") if (p + k) % 2 == 0 else ("peer", "ours"):
                    if who == "ours":
                        t0 = time.perf_counter()
                        got = measurer[img.dtype].measure(img).result
                        ms.append((time.perf_counter() - t0) * 1e3)
                        if p == 0 and isinstance(got, PoseResult):
                            named.append(len(got.targets))
                            if ref is not None:
                                d_mm[k], deg = pose_difference(got.T_field_camera, ref.T_field_camera)
                                d_deg[k] = deg
                    elif ref is not None:
                        ids_uv = (list(ref.targets.ids), np.asarray(ref.targets.uv_px))
                        thr = PEER_THRESHOLD_DN * (16 if img.dtype == np.uint16 else 1)
                        T, s = _peer(img, ids_uv, xyz, fit, thr)
                        peer_ms.append(s * 1e3)
                        if p == 0 and T is not None:
                            peer_d[k] = pose_difference(T, ref.T_field_camera)[0]
        posed = f"{len(named)}/{len(shown)}"
        dm, pm, nan = list(d_mm.values()), list(peer_d.values()), float("nan")
        lines.append(
            f"| {name} | {posed} | {_q(ms, 0.5):.1f} | {_q(ms, 0.99):.1f} | {_q([float(n) for n in named], 0.5):.0f} "
            f"| {_q(dm, 0.5):.3f} / {max(dm, default=nan):.3f} | {max(d_deg.values(), default=nan):.4f} "
            f"| {len(pm)}/{len(shown)} | {_q(peer_ms, 0.5):.1f} "
            f"| {_q(pm, 0.5):.3f} / {max(pm, default=nan):.3f} | {_q(peer_ms, 0.5) / _q(ms, 0.5):.2f} |"
        )
    lines += [
        "",
        f"{len(images)} real images of MicMac's coded panel (2000×1333, 8 bit; `{data.name}`), "
        f"{passes} passes, posecell and the peer in turn, one core; Δ pose: from the pose posecell gives the "
        "image as it is (no ground truth); the peer is given the identities and its threshold. " + "; ".join(said),
    ]
    return "\n".join(lines)
