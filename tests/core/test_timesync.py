"""Clock mapping, pose interpolation and latency estimation on seeded simulated clocks."""

from __future__ import annotations

import numpy as np
import pytest

from service.core.geometry.frames import T_from_rotvec, pose_difference
from service.core.pose.timesync import ClockMapper, estimate_time_offset_s, fit_lower_envelope, pose_at


def _events(rng, n, rate_hz, offset_ns, drift_ppm, latency_ns, jitter_ns):
    """Device event times and their host arrivals: true host time + latency + exponential jitter."""
    t_host_event = np.arange(n) * 1e9 / rate_hz + 5e9 + rng.uniform(0, 1e6, n)
    t_device = (t_host_event - offset_ns) * (1.0 + drift_ppm * 1e-6)
    arrival = t_host_event + latency_ns + rng.exponential(jitter_ns, n)
    return t_host_event, t_device, arrival


@pytest.mark.parametrize("drift_ppm", [-80.0, 0.0, 45.0])
def test_lower_envelope_maps_device_events_to_host_within_jitter_floor(rng, drift_ppm):
    t_event, t_dev, arrival = _events(rng, 300, 30.0, 1.23e15, drift_ppm, 2e6, 1.5e6)
    fit = fit_lower_envelope(t_dev, arrival, min_latency_ns=2e6)
    err_ns = fit.host_from_device(t_dev) - t_event
    # the envelope touches the least-delayed events: errors of tens of µs, far below the 1.5 ms jitter
    assert np.max(np.abs(err_ns)) < 0.1e6
    assert abs(fit.drift_ppm + drift_ppm) < 5.0  # device runs fast by drift -> host rate is 1/(1+drift)
    assert 0.5e6 < fit.jitter_ns < 2.5e6


def test_least_squares_would_be_biased_by_the_mean_jitter(rng):
    # the reason for the envelope: a mean fit is late by the mean jitter, the envelope is not
    t_event, t_dev, arrival = _events(rng, 300, 30.0, 0.0, 0.0, 0.0, 3e6)
    mean_offset_err = np.mean(arrival - t_dev) - np.mean(t_event - t_dev)
    envelope_err = np.median(fit_lower_envelope(t_dev, arrival).host_from_device(t_dev) - t_event)
    assert mean_offset_err > 2e6
    assert abs(envelope_err) < 0.1e6


def test_clock_mapper_restarts_after_a_device_clock_reset(rng):
    t_event, t_dev, arrival = _events(rng, 100, 50.0, -7e9, 20.0, 1e6, 0.5e6)
    m = ClockMapper(window=64, min_latency_ns=1e6)
    for d, a in zip(t_dev, arrival, strict=True):
        m.add(d, a)
    assert abs(m.host_from_device(t_dev[-1]) - t_event[-1]) < 0.1e6
    # camera power-cycled: its counter starts again near zero
    m.add(1000.0, arrival[-1] + 20e6)
    assert m.n == 1
    assert m.host_from_device(1000.0) == pytest.approx(arrival[-1] + 20e6 - 1e6)


def test_clock_mapper_needs_an_event_before_mapping():
    with pytest.raises(ValueError, match="no clock events"):
        ClockMapper().host_from_device(0.0)


def _circle(t_s):
    a = 2 * np.pi * t_s / 10.0
    return [T_from_rotvec([0, 0, a], [300 * np.cos(a), 300 * np.sin(a), 500]) for a in np.atleast_1d(a)]


def test_pose_at_interpolates_between_samples_and_refuses_gaps():
    t = np.arange(0, 1, 0.002)
    Ts = np.array(_circle(t))
    T_mid = pose_at(0.5011, t, Ts, max_gap=0.01)
    dpos, dang = pose_difference(T_mid, _circle(0.5011)[0])
    assert dpos < 1e-3 and dang < 1e-6  # chord error of a 300 mm circle over 2 ms is sub-µm
    assert pose_at(1.5, t, Ts, max_gap=0.01) is None  # far past the newest sample
    assert pose_at(-0.1, t, Ts, max_gap=0.01) is None
    gap = np.r_[t[:100], t[200:]]
    assert pose_at(0.3, gap, np.r_[Ts[:100], Ts[200:]], max_gap=0.01) is None
    # a query just past the newest report is extrapolated (the next sample is still in flight)
    T_ahead = pose_at(t[-1] + 0.001, t, Ts, max_gap=0.01)
    assert pose_difference(T_ahead, _circle(t[-1] + 0.001)[0])[0] < 1e-2
    # exactly on the first and the newest sample: those samples; no samples: nothing
    np.testing.assert_allclose(pose_at(t[0], t, Ts, max_gap=0.01), Ts[0], atol=1e-9)
    np.testing.assert_allclose(pose_at(t[-1], t, Ts, max_gap=0.01), Ts[-1], atol=1e-9)
    assert pose_at(0.5, [], np.zeros((0, 4, 4)), max_gap=0.01) is None
    # host nanoseconds (the pairing's times): the same pose as in seconds
    t_ns = 1_700_000_000e9 + t * 1e9
    T_ns = pose_at(1_700_000_000e9 + 0.5011e9, t_ns, Ts, max_gap=0.01e9)
    assert pose_difference(T_ns, T_mid)[0] < 1e-3


def test_time_offset_is_recovered_from_motion_with_a_constant_model_error(rng):
    t = np.linspace(0, 20, 400)
    offset_true = 0.0037
    p_rep = np.array([T[:3, 3] for T in _circle(t)])
    p_meas = np.array([T[:3, 3] for T in _circle(t - offset_true)]) + [0.8, -1.2, 0.4]
    p_meas += rng.normal(0, 0.02, p_meas.shape)
    fit = estimate_time_offset_s(t, p_meas, p_rep)
    assert abs(fit.offset_s - offset_true) < 4 * fit.sigma_s + 1e-5
    assert 1e-6 < fit.sigma_s < 1e-4
    assert np.allclose(fit.bias_mm, [0.8, -1.2, 0.4], atol=0.05)


def test_time_offset_needs_motion():
    t = np.linspace(0, 1, 50)
    p = np.tile([100.0, 0.0, 0.0], (50, 1))
    with pytest.raises(ValueError, match="hardly moved"):
        estimate_time_offset_s(t, p, p)
