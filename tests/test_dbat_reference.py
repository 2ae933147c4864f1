"""posecell's self-calibrating bundle adjustment against DBAT's on the same real observations.

Data: ../shared/data/dbat-camcal (DBAT, Börlin & Grussenmeyer, BSD-style licence): PhotoModeler's
export of 2074 image points (4148 coordinates, sigma 0.1 px) of a calibration sheet in 21 images
(2272 x 1704 px), the four control points 1001-1004 (a unit square, the datum) and DBAT's result
(c, principal point, K1-K3, P1, P2 and an aspect parameter estimated; sigma0 0.16148 px,
redundancy 3725). posecell runs on the files in place, with DBAT's setup: the control points fixed,
the same nine interior unknowns (posecell's affinity B1 for DBAT's aspect, skew and B2 fixed), no
gross-error rejection (DBAT rejects none), start values from the control points alone (c = 7.3 mm,
no distortion, the principal point at the centre; the other 96 points by forward intersection).

Both residual forms are checked: ``ideal`` is DBAT's own (ideal-coordinate residuals), ``pixel``
posecell's default (measured minus predicted pixels); the two weigh points near the corners
differently by the local scale of the lens correction, so they are two estimates of the same camera.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from service.core.calib.bundle import Datum, calibrate_camera
from service.store.formats_dbat import posecell_parameters, read_dbat_control, read_dbat_report, read_pm_export
from tests.conftest import shared_data

DATA = "dbat-camcal"
FREE = ("c_mm", "x0_mm", "y0_mm", "K1", "K2", "K3", "P1", "P2", "B1")


@pytest.fixture(scope="module")
def dbat():
    data = shared_data(DATA)
    project = read_pm_export(data / "camcal-pmexport.txt")
    control = read_dbat_control(data / "camcal-fixed.txt")
    report = read_dbat_report(data / "camcal-dbatreport.txt")
    return project, control, report


@pytest.fixture(scope="module", params=["ideal", "pixel"])
def solution(request, dbat):
    project, control, report = dbat
    start = dataclasses.replace(project.camera, c_mm=7.3, x0_mm=0.0, y0_mm=0.0)
    result = calibrate_camera(
        start,
        control,
        project.images,
        free=FREE,
        datum=Datum(control=control.ids),
        sigma_px=project.sigma_px,
        residual_space=request.param,
        reject_outliers=False,
    )
    return request.param, result, posecell_parameters(report, project.camera), report


def test_the_export_reads_as_dbat_reads_it(dbat):
    project, control, report = dbat
    assert (project.width, project.height, len(project.images)) == (2272, 1704, 21)
    assert sum(len(im.ids) for im in project.images) * 2 == 4148  # DBAT's observation count
    assert len(project.object_points) == 100 and project.sigma_px == 0.1
    assert control.ids == ("1001", "1002", "1003", "1004")
    assert report["sigma0_px"] == 0.16148 and report["redundancy"] == 3725
    assert report["cc"] == (7.457, 0.00105)


def test_bundle_reproduces_dbats_camera_within_its_sigma(solution):
    space, result, reference, _ = solution
    assert result.redundancy == 3725  # the same unknowns and observations as DBAT
    for name, (value, sigma) in reference.items():
        got = getattr(result.camera, name)
        assert abs(got - value) < sigma, (space, name, got, value, sigma)
        assert 0.8 < result.sigma[name] / sigma < 1.25, (space, name, result.sigma[name], sigma)


def test_bundle_reproduces_dbats_sigma0_within_5_percent(solution):
    space, result, _, report = solution
    assert abs(result.sigma0_px / report["sigma0_px"] - 1.0) < 0.05, (space, result.sigma0_px)
    if space == "ideal":  # DBAT's own residuals: the same minimum
        assert abs(result.sigma0_px / report["sigma0_px"] - 1.0) < 0.002


def test_dbats_converted_camera_maps_the_sensor_as_posecells_does(solution):
    # The same ideal coordinates, through DBAT's converted camera and through posecell's, land on
    # the same pixels over the whole sensor (corners included, where the lens moves them ~116 px).
    space, result, reference, _ = solution
    converted = dataclasses.replace(result.camera, sigma=None, **{n: v for n, (v, _) in reference.items()})
    grid = result.camera.pixel_grid(9, 7)
    shift = converted.pixel_from_ideal(result.camera.ideal_from_pixel(grid)) - grid
    assert np.abs(shift).max() < 0.2, (space, np.abs(shift).max())


# -- the readers, on a miniature export (no data needed) -----------------------------------------

MINI_EXPORT = """Bundle Soln Mini
 0.000500 1 200 100
 1.00000  0.10000 10.00000 100.00000 100.00000 100.00000 20.00000 20.00000 20.00000
 7.4000  1.0000  0.5000 2.00000 1.00000 0.00100 0.00000 0.00000 0.00000 0.00000
 0.00000  0.00725  0.00544 0.500000 0.500000 0.001000 0.000100 0.000100 0.001000 0.001000
   0 dir\\\\img0.JPG
   0    0.455    1.794    1.468 -179.839   -1.181  -39.420
   0   0.0002   0.0002   0.0002   0.0029   0.0080   0.0090

   0   7.400   1.000   0.500 2.00000 1.00000 0.00100 0.00000 0.00000 0.00000 0.00000
   0  0.00000  0.00725  0.00544 0.500000 0.500000 0.001000 0.000100 0.000100 0.001000 0.001000


       2    0.28573    1.14303   -0.00098   0.000042   0.000041   0.000072
    1001    0.00000    1.00000    0.00000   0.545506   0.545506   0.545506

   0        2  100.5000   50.5000  0.10000  0.10000
   0     1001   10.2500   20.0000  0.10000  0.10000

   1    1        2
"""


def test_export_reader_converts_corner_origin_pixels_and_metres(tmp_path):
    path = tmp_path / "mini-pmexport.txt"
    path.write_text(MINI_EXPORT)
    project = read_pm_export(path)
    im = project.images[0]
    assert im.name == "img0.JPG" and im.ids == ("2", "1001")
    assert np.allclose(im.uv, [[100.0, 50.0], [9.75, 19.5]])  # PhotoModeler's (0.5, 0.5) is posecell's (0, 0)
    assert np.allclose(project.object_points.xyz[0], [285.73, 1143.03, -0.98])  # m -> mm
    cam = project.camera
    assert cam.pixel_size_mm == (0.01, 0.01) and cam.c_mm == 7.4
    # the principal point 1.0 mm from the corner is pixel 99.5, the sensor centre 99.5: x0 = 0
    assert abs(cam.x0_mm) < 1e-12 and abs(cam.y0_mm - 0.0) < 1e-12
