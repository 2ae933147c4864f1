"""The replay camera: recorded (or pre-rendered) frames delivered on a steady clock.

Sources (``options = { source = ... }``):

- a folder: every ``*.png``, ``*.tif``/``*.tiff`` and ``*.pgm`` in it (not in sub-folders),
  8 or 16 bit grey (colour is converted to grey), read at ``open`` with
  ``cv2.imread(..., cv2.IMREAD_UNCHANGED)`` into memory and played in name order; 16-bit frames
  are reported as ``Mono12`` when none passes 4095 (a 12-bit camera's), else ``Mono16``.
  An optional ``timestamps.csv`` beside them gives each frame's device time: the
  header ``file,t_ns`` (whole ns; ``name`` for ``file`` and ``t_s`` seconds for ``t_ns``
  are accepted too, as in ``posecell calibrate``'s camera folders; other columns are
  ignored), then one row per image file name; every image needs a row, rows of
  other files are ignored, and the times must increase in name order.
- ``"sim"``: the simulated cell's motion, rendered once ahead in a child process
  (``replay_render``; multiprocessing ``spawn``) into a file-backed array in
  ``/dev/shm``; the serving process only copies frames out of it. ``n_frames``
  frames are rendered at the first ``configure`` (or ``fetch``), one per frame
  period of ``render_rate_hz`` (default: the configured ``frame_rate_hz``), at the
  configured exposure and pixel format, with the ring light lit (a later rate plays
  them faster or slower: they are not rendered again). Each frame's ``meta``
  carries the truth, ``T_field_camera`` (mm), and ``t_cell_s``. ``spawn`` runs the
  main module again in the child: a script needs its ``if __name__ == "__main__"``.

Timing: free run delivers slot ``k`` at ``t0 + k / frame_rate_hz`` on
``time.monotonic_ns`` (``t0`` = the last ``configure``), so sleeping late never
drifts the rate. A consumer that falls behind gets the frames of up to
``n_buffers`` missed slots at once (a camera's buffer pool) and loses older ones,
which show as gaps in ``seq``. A software trigger delivers the next frame
stamped at the trigger. ``t_host_ns`` = ``t_exposure_host_ns`` = the scheduled
instant (a replay has no exposure or transfer of its own); ``t_device_ns`` is the
recorded time (plus, on the p-th pass of a loop, p times the recording's span
and one recorded period, so it keeps increasing), else the scheduled instant.
With ``loop = false`` the camera stops delivering (timeouts) after the last frame. With
``loop = "bounce"`` it plays the frames forward, then backward, and so on: the motion
stays continuous where a wrap jumps from the last pose to the first (the ROI tracking
then measures the next two frames in full: over 100 rendered frames 2 % of the frames, which
made the p99 of ``posecell bench service``; it bounces).
The device time of a bounce keeps increasing by the recorded intervals, in either direction.

``timing = "recorded"`` (a folder of a posecell recording, ``service/runtime/recorder.py``) plays
each frame at its recorded time instead, on the clock of :mod:`drivers.replay_clock` that the
``replay`` robot plays the recording's ``robot.csv`` on: frames and robot samples in step, as
recorded (``frame_rate_hz`` is then not used; ``loop`` true or false, not ``"bounce"``).

Settings that cannot apply to recorded images: ``gain_db`` other than 0 and a
hardware trigger raise ``FeatureUnsupported``, as do a pixel format other than
the recording's and, for ``"sim"``, another exposure than the one rendered
(the frames would have to be rendered again: reopen the camera). A folder's
frames are stamped with the configured ``exposure_us`` (the recording's, as the
operator states it); an exposure step (a ``configure`` changing only the
exposure, as the exposure control makes) labels the frames delivered after it
and keeps the frame clock and the triggers waiting. ROI crops. The strobe is
accepted and has no effect: the ring light of a recording was what it was;
``info.features`` has no ``strobe``.

Not modelled: exposure, readout and transfer latency, jitter, packet loss, a device
clock's offset and drift, any link to a robot (a replay is not the robot's pose now).
"""

from __future__ import annotations

import collections
import csv
import io
import os
import threading
import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from drivers.base import (
    CameraInfo,
    CameraSettings,
    DriverDisconnected,
    DriverInitError,
    DriverTimeout,
    FeatureUnsupported,
    Frame,
    TriggerMode,
)
from drivers.replay_clock import ReplayClock, clock_of, recording_of

IMAGE_SUFFIXES = (".png", ".tif", ".tiff", ".pgm")
TIMESTAMPS_FILE = "timestamps.csv"
MAX_RATE_HZ = 10_000.0
DEFAULT_RATE_HZ = 30.0
_BIT_DEPTH = {"Mono8": 8, "Mono12": 12, "Mono16": 16}


@dataclass
class _Recording:
    frames: NDArray[Any]  # (N, H, W) uint8 or uint16: in memory, or mapped from the render file
    t_ns: NDArray[np.int64] | None  # (N,) recorded device times, ns
    loop_ns: int | None  # added to t_ns on each pass of a loop
    meta: list[dict[str, Any]]  # per frame
    pixel_formats: tuple[str, ...]  # the formats it can be delivered as (the first is reported)
    exposure_us: float | None  # the exposure the frames were taken with, when known
    # a posecell recording's columns beside t_ns (its host arrival): device time and the exposure
    # instant on the recording host's clock, -1 where the camera had none
    t_device_ns: NDArray[np.int64] | None = None
    t_exposure_ns: NDArray[np.int64] | None = None


def _read_image(path: Path) -> NDArray[Any]:
    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise DriverInitError(f"replay image {path} cannot be read as an image (PNG, TIFF or PGM, 8 or 16 bit)")
    if image.ndim == 3:
        image = cv2.cvtColor(image, cv2.COLOR_BGRA2GRAY if image.shape[2] == 4 else cv2.COLOR_BGR2GRAY)
    if image.dtype not in (np.uint8, np.uint16):
        raise DriverInitError(f"replay image {path} has pixel type {image.dtype}, not 8 or 16 bit grey")
    return image


def _read_timestamps(path: Path, names: list[str]) -> NDArray[np.int64]:
    try:
        rows = list(csv.reader(io.StringIO(path.read_text(encoding="utf-8"))))
    except (OSError, UnicodeDecodeError) as e:
        raise DriverInitError(f"{path} cannot be read ({e})") from e
    header = [c.strip().lower() for c in rows[0]] if rows else []
    if len(header) < 2 or header[0] not in ("file", "name") or header[1] not in ("t_ns", "t_s"):
        raise DriverInitError(f"{path}: the first row must be the header 'file,t_ns' (or 'name,t_ns', 'file,t_s')")
    stamps: dict[str, int] = {}
    for n, row in enumerate(rows[1:], start=2):
        cells = [c.strip() for c in row]
        if not any(cells) or cells[0].startswith("#"):
            continue
        try:
            stamps.setdefault(cells[0], int(cells[1]) if header[1] == "t_ns" else round(float(cells[1]) * 1e9))
        except (IndexError, ValueError, OverflowError):
            raise DriverInitError(f"{path}: row {n} is not 'file,{header[1]}'") from None
    missing = [name for name in names if name not in stamps]
    if missing:
        more = f" and {len(missing) - 1} more images" if len(missing) > 1 else ""
        raise DriverInitError(f"{path} has no timestamp for {missing[0]}{more}")
    t = np.array([stamps[name] for name in names], dtype=np.int64)
    for i in np.flatnonzero(np.diff(t) <= 0)[:1] + 1:
        raise DriverInitError(
            f"{path}: the timestamp of {names[i]} ({t[i]} ns) is not after that of {names[i - 1]} "
            f"({t[i - 1]} ns); frames play in name order"
        )
    return t


def load_folder(folder: Path) -> _Recording:
    """The recording in ``folder`` (see the module docstring); raises ``DriverInitError`` naming the bad file."""
    if not folder.is_dir():
        raise DriverInitError(f"replay folder {folder} does not exist or is not a folder")
    paths = sorted((p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES and p.is_file()), key=str)
    if not paths:
        raise DriverInitError(f"replay folder {folder} holds no images ({', '.join(IMAGE_SUFFIXES)})")
    first = _read_image(paths[0])
    frames = np.empty((len(paths), *first.shape), dtype=first.dtype)
    frames[0] = first
    for k, p in enumerate(paths[1:], start=1):
        image = _read_image(p)
        if image.shape != first.shape or image.dtype != first.dtype:
            raise DriverInitError(
                f"replay image {p} is {image.shape[1]} x {image.shape[0]} px {image.dtype}, but {paths[0].name} "
                f"is {first.shape[1]} x {first.shape[0]} px {first.dtype}: every frame of a replay needs one format"
            )
        frames[k] = image
    names = [p.name for p in paths]
    t_ns, loop_ns = None, None
    if (folder / TIMESTAMPS_FILE).is_file():
        t_ns = _read_timestamps(folder / TIMESTAMPS_FILE, names)
        if len(t_ns) > 1:
            loop_ns = int(t_ns[-1] - t_ns[0] + np.median(np.diff(t_ns)))
    # 16-bit frames that never pass 4095 are a 12-bit camera's (a posecell recording of a Mono12
    # camera): reported as Mono12, so that the measurement takes their 12 bits
    formats = (
        ("Mono8",) if first.dtype == np.uint8 else ("Mono12", "Mono16") if frames.max() < 4096 else ("Mono16", "Mono12")
    )
    frames.flags.writeable = False  # lent to every frame as it is (see ReplayCamera._frame)
    extra = _recorded_columns(folder / TIMESTAMPS_FILE, names) if t_ns is not None else (None, None)
    return _Recording(frames, t_ns, loop_ns, [{"file": n} for n in names], formats, None, *extra)


def _recorded_columns(path: Path, names: list[str]) -> tuple[NDArray[np.int64] | None, NDArray[np.int64] | None]:
    """A posecell recording's ``t_device_ns`` and ``t_exposure_host_ns`` columns (-1 where empty), if it has them."""
    rows = {r["file"]: r for r in csv.DictReader(io.StringIO(path.read_text(encoding="utf-8"))) if r.get("file")}
    out: list[NDArray[np.int64] | None] = []
    for column in ("t_device_ns", "t_exposure_host_ns"):
        try:
            out.append(np.array([int(rows[n][column] or -1) for n in names], dtype=np.int64))
        except (KeyError, TypeError, ValueError):  # not a posecell recording's file: the columns are not used
            out.append(None)
    return out[0], out[1]


class ReplayCamera:
    """Frames of a folder, or of the simulated cell rendered ahead, on a steady clock (module docstring).

    Parameters
    ----------
    source : a folder of images, or ``"sim"``
    loop : True: play the frames again from the first once the last is delivered; False: stop
        there; "bounce": play them backward from there, then forward again (module docstring)
    n_buffers : missed free-run frames still delivered to a consumer that fell behind
    n_frames, render_rate_hz, seed : ``"sim"``: frames to render, at this rate (default: the
        configured frame rate), and the seed of the image noise
    cell, cell_config : ``"sim"``: the simulated cell (its ``config`` is rendered) or its
        ``CellConfig`` fields; the default cell when neither is given
    render_timeout_s : ``"sim"``: the longest the rendering may take
    """

    def __init__(
        self,
        source: str | os.PathLike[str] = "sim",
        loop: bool | str = True,
        n_buffers: int = 8,
        n_frames: int = 100,
        render_rate_hz: float | None = None,
        seed: int = 1,
        cell: Any = None,
        cell_config: dict[str, Any] | None = None,
        render_timeout_s: float = 600.0,
        serial: str | None = None,
        timing: str = "rate",
    ) -> None:
        self.sim = str(source) == "sim"
        if timing not in ("rate", "recorded") or (timing == "recorded" and (self.sim or loop == "bounce")):
            raise ValueError(
                f'timing must be "rate" or "recorded" (a recording\'s folder, loop true or false), got {timing!r}'
            )
        self.timing = timing
        self._clock: ReplayClock | None = None
        self.source = "sim" if self.sim else Path(source).expanduser()
        if int(n_buffers) < 1 or int(n_frames) < 1:
            raise ValueError(f"n_buffers and n_frames must be at least 1, got {n_buffers} and {n_frames}")
        if loop not in (True, False, "bounce"):
            raise ValueError(f'loop must be true, false or "bounce", got {loop!r}')
        self.loop, self.bounce = loop is not False, loop == "bounce"
        self.n_buffers, self.n_frames = int(n_buffers), int(n_frames)
        self.render_rate_hz, self.seed, self.render_timeout_s = render_rate_hz, int(seed), float(render_timeout_s)
        self._cell_config = dict(cell.config.to_dict() if cell is not None else cell_config or {})
        self._sensor_hw = None if cell is None else (cell.camera.height, cell.camera.width)
        name = "SIM" if self.sim else Path(source).name
        self._serial = serial or f"REPLAY-{name}"
        self._settings = CameraSettings(strobe=None)
        self._rec: _Recording | None = None
        self._open = False
        self._closing = threading.Event()
        self._cond = threading.Condition()  # trigger() may come from another thread than fetch()
        self._triggers: collections.deque[int] = collections.deque()
        self._j_next = 0  # the next frame, counted over all passes
        self._anchor()  # the free-run schedule: slot k (frame j0 + k) at t0 + k periods

    # --- CameraDriver -------------------------------------------------------------------------

    @property
    def info(self) -> CameraInfo:
        h, w = self._require_open()
        if self._settings.roi is not None:
            w, h = self._settings.roi[2:]
        rec = self._rec
        fmt = self._settings.pixel_format or (rec.pixel_formats[0] if rec is not None else "Mono8")
        features = ("frame_rate", "trigger", "roi")
        return CameraInfo("replay", f"posecell replay of {self.source}", self._serial, w, h, fmt, features)

    def open(self) -> None:
        if self._open:
            return
        self._closing.clear()
        if not self.sim:
            self._rec = load_folder(Path(self.source))
            if self.timing == "recorded":
                if self._rec.t_ns is None:
                    raise DriverInitError(
                        f"replay folder {self.source} has no timestamps.csv: it cannot play recorded time"
                    )
                self._clock = clock_of(recording_of(Path(self.source)))
        elif self._sensor_hw is None:
            from service.sim.scene import reference_camera  # the only scene a CellConfig names

            cam = reference_camera()
            self._sensor_hw = (cam.height, cam.width)
        self._open = True
        self._j_next = 0
        self._anchor()

    def configure(self, settings: CameraSettings) -> None:
        h, w = self._require_open()
        rec = self._rec
        if settings.trigger is TriggerMode.HARDWARE:
            raise FeatureUnsupported("TriggerMode", "a replay has no trigger input line (free run or software only)")
        if settings.frame_rate_hz is not None and not 0 < settings.frame_rate_hz <= MAX_RATE_HZ:
            raise FeatureUnsupported(
                "AcquisitionFrameRate", f"replay rate {settings.frame_rate_hz} Hz is outside 0..10k"
            )
        if settings.gain_db not in (None, 0.0):
            raise FeatureUnsupported("Gain", "a replay cannot apply gain to frames already taken (gain_db: none or 0)")
        if settings.roi is not None:
            x, y, rw, rh = settings.roi
            if x < 0 or y < 0 or rw <= 0 or rh <= 0 or x + rw > w or y + rh > h:
                raise FeatureUnsupported("ROI", f"ROI {settings.roi} is outside the replay's {w} x {h} frames")
        fmt = settings.pixel_format
        formats = rec.pixel_formats if rec is not None else tuple(_BIT_DEPTH)
        if fmt is not None and fmt not in formats:
            raise FeatureUnsupported("PixelFormat", f"the replay's frames are {formats[0]}, they cannot become {fmt}")
        if rec is not None and rec.exposure_us is not None and settings.exposure_us is not None:
            if abs(settings.exposure_us - rec.exposure_us) > 1e-3 * rec.exposure_us:
                raise FeatureUnsupported(
                    "ExposureTime",
                    f"the replay's frames were rendered at {rec.exposure_us:g} µs; another exposure needs them "
                    "rendered again (reopen the camera)",
                )
        if rec is None:
            self._rec = self._render(settings)
        with self._cond:
            old, self._settings = self._settings, settings
            # an exposure step only relabels the frames to come (a folder's): the clock and the triggers run on
            if rec is None or replace(settings, exposure_us=old.exposure_us, gain_db=old.gain_db) != old:
                self._triggers.clear()
                self._anchor()

    def fetch(self, timeout_s: float) -> Frame:
        self._require_open()
        rec = self._recording()
        deadline = time.monotonic_ns() + int(timeout_s * 1e9)
        if self._settings.trigger is TriggerMode.SOFTWARE:
            if self._ended(self._j_next, rec):
                self._timeout(deadline, timeout_s, rec, ended=True)
            with self._cond:
                while not self._triggers:
                    remaining_s = (deadline - time.monotonic_ns()) * 1e-9
                    if remaining_s <= 0:
                        raise DriverTimeout(f"no trigger for replay camera {self._serial} within {timeout_s:.3f} s")
                    self._cond.wait(remaining_s)
                t_ns = self._triggers.popleft()
            j = self._j_next
        elif self._clock is not None:
            j, t_ns = self._due_recorded(time.monotonic_ns(), rec)
            if self._ended(j, rec) or t_ns > deadline:
                self._timeout(deadline, timeout_s, rec, ended=self._ended(j, rec))
            wait_s = (t_ns - time.monotonic_ns()) * 1e-9
            if wait_s > 0:
                time.sleep(wait_s)
            self._require_open()
        else:
            k = self._due_slot(time.monotonic_ns())
            j, t_ns = self._j0 + k, self._slot_ns(k)
            if self._ended(j, rec) or t_ns > deadline:
                self._timeout(deadline, timeout_s, rec, ended=self._ended(j, rec))
            wait_s = (t_ns - time.monotonic_ns()) * 1e-9
            if wait_s > 0:
                time.sleep(wait_s)
            self._require_open()  # closed while it waited
            self._k = k + 1
        self._j_next = j + 1
        return self._frame(rec, j, t_ns)

    def try_fetch(self) -> Frame | None:
        self._require_open()
        now = time.monotonic_ns()
        if self._settings.trigger is TriggerMode.SOFTWARE:
            with self._cond:
                ready = bool(self._triggers)
        elif self._clock is not None:
            rec = self._recording()
            ready = not self._ended(self._j_next, rec) and self._due_recorded(now, rec)[1] <= now
        else:
            ready = self._slot_ns(self._due_slot(now)) <= now
        if not ready:
            return None
        try:
            return self.fetch(timeout_s=0.0)
        except DriverTimeout:  # the replay has ended (loop = false)
            return None

    def trigger(self) -> None:
        self._require_open()
        if self._settings.trigger is not TriggerMode.SOFTWARE:
            raise FeatureUnsupported("TriggerSoftware", "software trigger needs trigger mode 'software'")
        with self._cond:
            self._triggers.append(time.monotonic_ns())
            self._cond.notify_all()

    def close(self) -> None:
        self._open = False
        self._closing.set()
        self._rec = None  # a fetch still copying keeps its own reference to the frames

    # --- internals ----------------------------------------------------------------------------

    def _require_open(self) -> tuple[int, int]:
        if not self._open:
            raise DriverDisconnected(f"replay camera {self._serial} is not open")
        if self._rec is not None:
            return self._rec.frames.shape[1:]
        assert self._sensor_hw is not None
        return self._sensor_hw

    def _recording(self) -> _Recording:
        rec = self._rec
        if rec is None:  # "sim", fetched before any configure: render with the settings it has
            rec = self._rec = self._render(self._settings)
            self._anchor()
        return rec

    def _anchor(self) -> None:
        self._t0_ns, self._j0, self._k = time.monotonic_ns(), self._j_next, 0
        self._period_ns = 1e9 / (self._settings.frame_rate_hz or DEFAULT_RATE_HZ)

    def _slot_ns(self, k: int) -> int:
        return self._t0_ns + round(k * self._period_ns)

    def _due_slot(self, now_ns: int) -> int:
        """The slot to deliver next: the next one, or the oldest still "buffered" when far behind."""
        current = (now_ns - self._t0_ns) // self._period_ns
        return max(self._k, int(current) - self.n_buffers + 1)

    def _recorded_ns(self, rec: _Recording, j: int) -> int:
        """Where the ``j``-th frame plays on the replay clock (``timing = "recorded"``)."""
        assert self._clock is not None and rec.t_ns is not None
        n = len(rec.frames)
        return int(self._clock.host_ns(int(rec.t_ns[j % n]), j // n))

    def _due_recorded(self, now_ns: int, rec: _Recording) -> tuple[int, int]:
        """The next frame on the replay clock, or the oldest still "buffered" when far behind."""
        j = self._j_next
        n = len(rec.frames)
        if self.loop and self._recorded_ns(rec, j) < now_ns - 2 * self._clock.span_ns:  # type: ignore[union-attr]
            j += ((now_ns - self._recorded_ns(rec, j)) // self._clock.span_ns - 1) * n  # type: ignore[union-attr]
        while not self._ended(j + self.n_buffers, rec) and self._recorded_ns(rec, j + self.n_buffers) <= now_ns:
            j += 1
        return j, self._recorded_ns(rec, j)

    def _ended(self, j: int, rec: _Recording) -> bool:
        return not self.loop and j >= len(rec.frames)

    def _timeout(self, deadline_ns: int, timeout_s: float, rec: _Recording, ended: bool) -> None:
        time.sleep(max(0.0, (deadline_ns - time.monotonic_ns()) * 1e-9))
        why = f" (all {len(rec.frames)} frames were played, loop = false)" if ended else ""
        raise DriverTimeout(f"no frame from replay camera {self._serial} within {timeout_s:.3f} s{why}")

    def _frame(self, rec: _Recording, j: int, t_ns: int) -> Frame:
        i, p, elapsed_ns = self._index(rec, j)
        if self._settings.roi is None:
            # a read-only view, not a copy: a recording is never written or reused, so the frame may
            # hold it (a camera's buffer pool is another matter); at 500 Hz the copy was a fifth of a core
            image = rec.frames[i].view(np.ndarray)
        else:
            x, y, w, h = self._settings.roi
            image = np.array(rec.frames[i, y : y + h, x : x + w])  # a contiguous copy, as a camera's ROI
        t_device: int | None = t_ns
        if rec.t_ns is not None:
            t_device = int(rec.t_ns[0]) + elapsed_ns
        t_exposure: int | None = t_ns
        if self._clock is not None:  # the recorded stamps, on the replay clock: the service aligns them as it did live
            t_device, t_exposure = None, None
            loop_ns = p * self._clock.span_ns
            if rec.t_device_ns is not None and rec.t_device_ns[i] >= 0:
                t_device = int(rec.t_device_ns[i]) + loop_ns
            if rec.t_exposure_ns is not None and rec.t_exposure_ns[i] >= 0:
                t_exposure = int(self._clock.host_ns(int(rec.t_exposure_ns[i]), p))
        exposure = rec.exposure_us if rec.exposure_us is not None else self._settings.exposure_us or 0.0
        meta = {**rec.meta[i], "replay_index": i, "replay_pass": p}
        return Frame(image, j & 0xFFFF_FFFF, t_ns, t_device, exposure, t_exposure_host_ns=t_exposure, meta=meta)

    def _index(self, rec: _Recording, j: int) -> tuple[int, int, int]:
        """The ``j``-th frame delivered: (its index in the recording, its pass, the recorded time since
        the first frame's summed over the passes, ns, 0 without recorded times: it never runs back)."""
        n, t = len(rec.frames), rec.t_ns
        if not self.bounce or n == 1:
            i, p = j % n, j // n
            return i, p, 0 if t is None else int(t[i] - t[0]) + p * (rec.loop_ns or round(self._period_ns))
        p, q = divmod(j, n - 1)  # passes of n - 1 steps: forward (even p) and backward (odd p)
        i = q if p % 2 == 0 else n - 1 - q
        if t is None:
            return i, p, 0
        within = int(t[i] - t[0]) if p % 2 == 0 else int(t[-1] - t[i])
        return i, p, p * int(t[-1] - t[0]) + within

    def _render(self, settings: CameraSettings) -> _Recording:
        from drivers.camera.replay_render import render_in_child
        from drivers.camera.sim import REFERENCE_EXPOSURE_US

        assert self._sensor_hw is not None
        fmt = settings.pixel_format or "Mono8"
        exposure_us = settings.exposure_us if settings.exposure_us is not None else REFERENCE_EXPOSURE_US
        period_s = 1.0 / (self.render_rate_hz or settings.frame_rate_hz or DEFAULT_RATE_HZ)
        frames, truths, t_cell_s = render_in_child(
            self._cell_config,
            (self.n_frames, *self._sensor_hw),
            _BIT_DEPTH[fmt],
            period_s,
            exposure_us / REFERENCE_EXPOSURE_US,
            self.seed,
            self._closing,
            self.render_timeout_s,
        )
        meta = [
            {"T_field_camera": T.tolist(), "t_cell_s": float(t), "lit": True}
            for T, t in zip(truths, t_cell_s, strict=True)
        ]
        t_rec = np.round(t_cell_s * 1e9).astype(np.int64)
        return _Recording(frames, t_rec, round(self.n_frames * period_s * 1e9), meta, (fmt,), exposure_us)
