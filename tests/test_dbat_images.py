"""posecell's own measurement of DBAT's 21 images against PhotoModeler's observations of them.

Data: ../shared/data/dbat-camcal (DBAT, Börlin & Grussenmeyer, BSD-style licence): 21 JPEGs
(2272 x 1704) of a PhotoModeler calibration sheet, ~100 printed black dots of 12-40 px radius, and
PhotoModeler's 2074 image observations of them. Not our kind of target (printed, dark on white,
large, JPEG-compressed): the images are inverted and measured with the default settings.
"""

from __future__ import annotations

import dataclasses
from functools import cache

import cv2
import numpy as np
import pytest
from scipy.spatial import cKDTree

from service.core.calib.bundle import Datum, calibrate_camera
from service.core.targets.detect import DetectSettings, detect_blobs
from service.store.formats_dbat import ImagePoints, PhotoModelerProject, read_dbat_control, read_pm_export
from tests.conftest import shared_data

DATA = "dbat-camcal"
MATCH_PX = 2.0  # one of our centres within this of PhotoModeler's observation: the same dot


@cache
def _project() -> PhotoModelerProject:
    return read_pm_export(shared_data(DATA) / "camcal-pmexport.txt")


@cache
def _measured(centre: str) -> list[tuple[ImagePoints, np.ndarray, np.ndarray]]:
    """Per image: PhotoModeler's observations, our centre matched to each ((n, 2) px, NaN where
    none), and whether the observation is of a control point (measured by PhotoModeler alone)."""
    data, project = shared_data(DATA), _project()
    control = set(read_dbat_control(data / "camcal-fixed.txt").ids)
    out = []
    for im in project.images:
        grey = cv2.imread(str(data / "images" / im.name), cv2.IMREAD_GRAYSCALE)
        blobs, _ = detect_blobs(np.ascontiguousarray(255 - grey), DetectSettings(centre=centre))
        d, j = cKDTree(blobs.uv).query(im.uv)
        ours = np.where((d < MATCH_PX)[:, None], blobs.uv[j], np.nan)
        out.append((im, ours, np.array([i in control for i in im.ids])))
    return out


def _found(centre: str) -> float:
    pairs = [(np.isfinite(ours[:, 0]) | ctrl) for _, ours, ctrl in _measured(centre)]
    return float(np.mean(np.concatenate(pairs)))


def _gaps(centre: str) -> np.ndarray:
    """Our centres' distances to PhotoModeler's observations of the same dots, px, less each image's
    median offset (the two place the pixel grid's origin differently)."""
    gaps = []
    for im, ours, ctrl in _measured(centre):
        ok = np.isfinite(ours[:, 0]) & ~ctrl
        diff = ours[ok] - im.uv[ok]
        gaps.append(np.linalg.norm(diff - np.median(diff, axis=0), axis=1))
    return np.concatenate(gaps)


def test_edge_centres_lie_closer_to_photomodelers_than_centroids():
    # An uneven print or light makes a dot's brightness uneven: the centroid follows it, the edge
    # does not (seen: 0.15 px median against 0.25)
    edge, centroid = np.median(_gaps("edge")), np.median(_gaps("centroid"))
    assert edge < 0.2 and edge < 0.7 * centroid, (edge, centroid)
    # The windows' asymmetry test, set for retro-reflective targets, rejects about half of these
    # large printed dots, whatever the centre (seen: 54 % of PhotoModeler's observations found)
    assert 0.5 < _found("edge") and abs(_found("edge") - _found("centroid")) < 0.02


def test_edge_centres_agree_with_photomodeler_and_the_bundle_is_as_consistent():
    # the same self-calibrating bundle (DBAT's set-up: control points fixed, nine interior
    # unknowns) on the dots both measured, with our centres and with PhotoModeler's
    data, project = shared_data(DATA), _project()
    control = read_dbat_control(data / "camcal-fixed.txt")
    ours_images, theirs_images = [], []
    for im, ours, ctrl in _measured("edge"):
        keep = np.isfinite(ours[:, 0]) | ctrl
        ids = tuple(np.array(im.ids)[keep])
        uv = np.where(ctrl[:, None], im.uv, ours)[keep]
        ours_images.append(dataclasses.replace(im, ids=ids, uv=uv))
        theirs_images.append(dataclasses.replace(im, ids=ids, uv=im.uv[keep]))
    start = dataclasses.replace(project.camera, c_mm=7.3, x0_mm=0.0, y0_mm=0.0)
    free = ("c_mm", "x0_mm", "y0_mm", "K1", "K2", "K3", "P1", "P2", "B1")

    def sigma0(images: list[ImagePoints]) -> float:
        r = calibrate_camera(
            start,
            control,
            images,
            free=free,
            datum=Datum(control=control.ids),
            sigma_px=project.sigma_px,
            residual_space="pixel",
            reject_outliers=False,
        )
        return float(r.sigma0_px)

    ours, theirs = sigma0(ours_images), sigma0(theirs_images)
    assert ours < 1.05 * theirs, (ours, theirs)  # seen: 0.1630 against 0.1631 px (centroids: 0.178)


@pytest.mark.parametrize("centre", ["edge", "centroid"])
def test_no_dot_is_found_twice(centre):
    for _, ours, _ in _measured(centre):
        found = ours[np.isfinite(ours[:, 0])]
        assert len(np.unique(np.round(found, 6), axis=0)) == len(found)
