"""Recording a session: the cameras' frames, and the robot's poses beside them, in the folder the replay plays.

A recording is what a user keeps of a cell to look at again: a run to analyse offline, a problem
to reproduce, real images to measure ``posecell`` against. It writes, under
``<state_dir>/recordings/<id>/``:

- ``<camera>/frame-000001.pgm`` … : every frame the camera delivered while it ran (or every
  ``every_n``-th), lossless, 8 or 16 bit as delivered: PGM by default (written as fast as the disk
  takes it), PNG or TIFF (half the size, but encoding costs tens of ms a frame);
- ``<camera>/timestamps.csv``: ``file,t_ns`` with each frame's arrival on the host's monotonic
  clock (the robot samples' clock below), then ``seq``, ``t_device_ns`` and
  ``t_exposure_host_ns`` (each empty where the camera gave none), ``exposure_us``: the raw stamps,
  so that a replay in step with the robot (``timing = "recorded"``) lets the service align the
  exposures as it did live. The ``replay`` camera plays the folder as it is
  (``options = { source = "<that folder>" }``) and ``posecell calibrate camera`` reads it;
- ``robot.csv``: every robot sample over the same span, ``t_host_ns,t_robot_s`` then
  ``T_base_flange`` as ``x_mm,y_mm,z_mm,rx_rad,ry_rad,rz_rad`` (a rotation vector) and the joints
  ``q1_rad`` … ``q6_rad``;
- ``recording.json``: what was asked, what was written, how it ended (``recording``, ``complete``,
  ``stopped``, ``failed`` with a sentence; a recording found still ``recording`` when the service
  starts was cut by a stop it did not see and is marked ``interrupted``).

The camera's thread only hands each frame (a reference: frames are never rewritten) to a bounded
queue; one writer thread per recording encodes and writes. A frame the queue has no room for (the
disk slower than the camera) is counted as ``dropped``, never silently missing: each camera's
``frames`` and ``dropped`` are in the summary, and the ``seq`` column shows where. The robot's
samples are copied from the driver's history every quarter second, so its ring buffer never has to
hold a whole recording. A recording stops itself, ``stopped`` with the reason, when the disk's free
space falls below ``min_free_bytes``.
"""

from __future__ import annotations

import contextlib
import csv
import json
import logging
import os
import queue
import re
import shutil
import threading
import time
from collections.abc import Callable, Mapping
from dataclasses import asdict, dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Any, Protocol

import cv2
import numpy as np

from drivers.base import Frame
from drivers.history import RobotHistory
from service.core.geometry.so3 import rotvec_from_T
from service.core.results import Reason
from service.store.formats import fsync_dir, write_json_atomic

log = logging.getLogger(__name__)

FORMATS = {"png": ".png", "tiff": ".tiff", "pgm": ".pgm"}
# PGM (the default) is the frame's bytes behind a header: ~0.5 ms a 1.3 MP frame on a slow 2-core VM,
# where PNG (compression 1, half the size: sensor noise compresses poorly) takes ~66 ms and TIFF ~34 ms
_ENCODE = {"png": [cv2.IMWRITE_PNG_COMPRESSION, 1], "tiff": [], "pgm": []}
QUEUE_FRAMES = 64  # frames waiting for the writer (~85 MB of 1.3 MP 8-bit frames)
ROBOT_PULL_S = 0.25  # the robot's samples copied from its history this often
ROBOT_TAIL_S = 0.1  # after the last frame, the samples still on their way are waited for
MIN_FREE_BYTES = 512 * 2**20
MANIFEST = "recording.json"
ROBOT_FILE = "robot.csv"
TIMESTAMPS_HEADER = ("file", "t_ns", "seq", "t_device_ns", "t_exposure_host_ns", "exposure_us")
ROBOT_HEADER = (
    "t_host_ns",
    "t_robot_s",
    "x_mm",
    "y_mm",
    "z_mm",
    "rx_rad",
    "ry_rad",
    "rz_rad",
    *(f"q{i}_rad" for i in range(1, 7)),
)
_ID = re.compile(r"^[0-9]{8}-[0-9]{6}(-[0-9]+)?$")


class RecordingError(Exception):
    """A recording cannot be started, found or changed; ``kind`` is not_found, busy, bad_input or storage."""

    def __init__(self, kind: str, message: str) -> None:
        super().__init__(message)
        self.kind, self.message = kind, message

    @property
    def reason(self) -> Reason:
        """The service's reason for it (the API's and the OPC UA methods')."""
        return _REASON_OF_KIND[self.kind]


_REASON_OF_KIND = {
    "not_found": Reason.not_found,
    "busy": Reason.busy,
    "bad_input": Reason.bad_input,
    "storage": Reason.storage_unavailable,
}


class Tappable(Protocol):
    """A camera channel that hands every frame it delivers to ``tap`` (``None``: to nobody)."""

    tap: Callable[[Frame], None] | None


@dataclass(frozen=True)
class RecordingRequest:
    """What to record: cameras (empty: all), at most ``max_frames`` a camera and ``max_seconds``."""

    cameras: tuple[str, ...] = ()
    max_frames: int = 1000
    max_seconds: float = 60.0
    every_n: int = 1
    format: str = "pgm"
    label: str = ""

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> RecordingRequest:
        """A request from JSON (the PLC's parameters); raises ``RecordingError`` (bad_input) saying what is wrong."""
        unknown = sorted(set(d) - {"cameras", "max_frames", "max_seconds", "every_n", "format", "label"})
        if unknown:
            raise RecordingError("bad_input", f"unknown parameter {unknown[0]!r}")
        cameras = d.get("cameras", [])
        if not isinstance(cameras, list) or not all(isinstance(c, str) for c in cameras):
            raise RecordingError("bad_input", "cameras must be a list of camera names")
        try:
            numbers = {k: d[k] for k in ("max_frames", "every_n", "max_seconds") if k in d}
            if any(isinstance(v, bool) or not isinstance(v, int | float) for v in numbers.values()):
                raise TypeError
            if any(k != "max_seconds" and not float(v).is_integer() for k, v in numbers.items()):
                raise TypeError
        except TypeError:
            raise RecordingError(
                "bad_input", "max_frames and every_n must be whole numbers, max_seconds a number"
            ) from None
        return cls(
            tuple(cameras),
            int(d.get("max_frames", cls.max_frames)),
            float(d.get("max_seconds", cls.max_seconds)),
            int(d.get("every_n", cls.every_n)),
            str(d.get("format", cls.format)),
            str(d.get("label", cls.label))[:200],
        )

    def check(self, known: list[str]) -> RecordingRequest:
        """The request with its cameras resolved; raises ``RecordingError`` saying what is wrong."""
        if self.format not in FORMATS:
            raise RecordingError("bad_input", f"format {self.format!r} is not one of {sorted(FORMATS)}")
        if not 1 <= self.max_frames <= 1_000_000 or not 1 <= self.every_n <= 10_000:
            raise RecordingError("bad_input", "max_frames must be in 1..1000000 and every_n in 1..10000")
        if not 0 < self.max_seconds <= 86_400:
            raise RecordingError("bad_input", "max_seconds must be in (0, 86400]")
        unknown = [c for c in self.cameras if c not in known]
        if unknown:
            raise RecordingError("not_found", f"no camera named {unknown[0]!r}; cameras: {known}")
        cameras = tuple(dict.fromkeys(self.cameras)) or tuple(known)
        if not cameras:
            raise RecordingError("bad_input", "the service has no camera to record")
        return RecordingRequest(cameras, self.max_frames, self.max_seconds, self.every_n, self.format, self.label)


@dataclass
class _CameraTrack:
    offered: int = 0  # frames the camera delivered while the recording ran
    accepted: int = 0  # put in the queue (each is written, unless writing fails)
    written: int = 0
    dropped: int = 0  # no room in the queue
    shape: list[int] = field(default_factory=list)
    dtype: str = ""
    exposure_us: float | None = None


class Recording:
    """One recording in progress (see the module docstring); ``offer`` is called by the camera threads."""

    def __init__(
        self,
        rec_id: str,
        folder: Path,
        request: RecordingRequest,
        history: Callable[[], RobotHistory | None],
        min_free_bytes: int,
        release: Callable[[Recording], None],
        on_end: Callable[[Recording], None],
    ) -> None:
        self.id, self.folder, self.request = rec_id, folder, request
        self.state, self.message = "recording", ""
        self.started_wall = datetime.now(UTC).isoformat(timespec="milliseconds")
        self.ended_wall: str | None = None
        self.tracks = {name: _CameraTrack() for name in request.cameras}
        self.robot_samples = 0
        self.settings: dict[str, Any] = {}  # what the service was set to (the manifest keeps it)
        self._history, self._min_free, self._release, self._on_end = history, min_free_bytes, release, on_end
        self._queue: queue.Queue[tuple[str, Frame] | None] = queue.Queue(QUEUE_FRAMES)
        self._deadline_ns = time.monotonic_ns() + int(request.max_seconds * 1e9)
        self._stopping = threading.Event()
        self._closed = False  # no frame is accepted any more
        self._lock = threading.Lock()
        self._robot_from_ns: int | None = None  # the next robot sample to copy is after this
        self._last_frame_ns = 0
        self._files: dict[str, Any] = {}  # per camera: its timestamps.csv, open for the writer
        self._robot_file: Any = None
        self._thread = threading.Thread(target=self._run, name=f"recording-{rec_id}", daemon=True)

    # --- the camera threads ------------------------------------------------------------------

    def offer(self, camera: str, frame: Frame) -> None:
        """A frame the camera delivered: queued for writing (never blocks), or counted as dropped."""
        with self._lock:
            track = self.tracks[camera]
            if self._closed or self._stopping.is_set() or time.monotonic_ns() >= self._deadline_ns:
                return
            track.offered += 1
            if (track.offered - 1) % self.request.every_n or track.accepted >= self.request.max_frames:
                return
            try:
                self._queue.put_nowait((camera, frame))
            except queue.Full:
                track.dropped += 1
                return
            track.accepted += 1
            if self._robot_from_ns is None:  # the robot's record starts a little before the first exposure
                self._robot_from_ns = frame.t_host_ns - int(ROBOT_TAIL_S * 1e9)

    # --- control -------------------------------------------------------------------------------

    def start(self) -> None:
        """Make the folders, open the CSV files with their headers, write the manifest; then record."""
        for name in self.request.cameras:
            (self.folder / name).mkdir(parents=True, exist_ok=False)
            f = (self.folder / name / "timestamps.csv").open("w", newline="", encoding="utf-8")
            self._files[name] = f
            csv.writer(f).writerow(TIMESTAMPS_HEADER)
        self._robot_file = (self.folder / ROBOT_FILE).open("w", newline="", encoding="utf-8")
        csv.writer(self._robot_file).writerow(ROBOT_HEADER)
        write_json_atomic(self.folder / MANIFEST, self.summary())
        self._thread.start()

    def stop(self, why: str = "") -> None:
        """End it now: the frames already accepted are written, then the robot's tail, then the manifest."""
        if why and not self.message:
            self.message = why
        self._stopping.set()
        with contextlib.suppress(queue.Full):  # a full queue: the writer is busy and sees the stop after it
            self._queue.put_nowait(None)  # wakes the writer

    def close_files(self) -> None:
        for f in (*self._files.values(), self._robot_file):
            if f is not None:
                with contextlib.suppress(OSError):
                    f.close()

    def join(self, timeout_s: float) -> None:
        self._thread.join(timeout_s)

    def summary(self) -> dict[str, Any]:
        cameras = {
            name: {**asdict(t), "folder": str(self.folder / name), "format": self.request.format}
            for name, t in self.tracks.items()
        }
        return {
            "id": self.id,
            "label": self.request.label,
            "state": self.state,
            "message": self.message,
            "started": self.started_wall,
            "ended": self.ended_wall,
            "folder": str(self.folder),
            "request": {**asdict(self.request), "cameras": list(self.request.cameras)},
            "cameras": cameras,
            "robot_samples": self.robot_samples,
            "settings": self.settings,
        }

    # --- the writer -----------------------------------------------------------------------------

    def _done(self) -> bool:
        if self._stopping.is_set() or time.monotonic_ns() >= self._deadline_ns:
            return True
        return all(t.accepted >= self.request.max_frames for t in self.tracks.values())

    def _run(self) -> None:
        files, robot = self._files, self._robot_file
        writers = {name: csv.writer(f) for name, f in files.items()}
        next_pull = time.monotonic() + ROBOT_PULL_S
        final = "failed"
        try:
            while True:
                try:
                    item = self._queue.get(timeout=0.05)
                except queue.Empty:
                    item = None
                if item is not None:
                    self._write(*item, writers[item[0]])
                if time.monotonic() >= next_pull:
                    next_pull = time.monotonic() + ROBOT_PULL_S
                    self._pull_robot(robot, time.monotonic_ns())
                    self._check_disk()
                if item is None and self._done() and self._queue.empty():
                    with self._lock:
                        self._closed = True
                    if self._queue.empty():
                        break
            time.sleep(ROBOT_TAIL_S)  # the samples of the last exposure are still on their way
            self._pull_robot(robot, self._last_frame_ns + int(ROBOT_TAIL_S * 1e9))
            final = "stopped" if self._stopping.is_set() else "complete"
        except OSError as e:  # a full disk, a folder removed under it: what is written stays
            final, self.message = "failed", f"writing the recording failed: {e}"
            with self._lock:
                self._closed = True
        finally:
            for f in (*files.values(), robot):
                with contextlib.suppress(OSError):  # written to the disk before the manifest says so
                    f.flush()
                    os.fsync(f.fileno())
                with contextlib.suppress(OSError):
                    f.close()
            self.ended_wall = datetime.now(UTC).isoformat(timespec="milliseconds")
            self._finish(final)

    def _write(self, camera: str, frame: Frame, writer: Any) -> None:
        track = self.tracks[camera]
        k = track.written + 1
        name = f"frame-{k:06d}{FORMATS[self.request.format]}"
        ok, data = cv2.imencode(FORMATS[self.request.format], frame.image, _ENCODE[self.request.format])
        if not ok:
            raise OSError(f"the frame could not be encoded as {self.request.format}")
        (self.folder / camera / name).write_bytes(data.tobytes())
        t_ns = frame.t_host_ns
        device = "" if frame.t_device_ns is None else str(frame.t_device_ns)
        exposure = "" if frame.t_exposure_host_ns is None else str(frame.t_exposure_host_ns)
        writer.writerow((name, t_ns, frame.seq, device, exposure, f"{frame.exposure_us:g}"))
        track.written = k
        if not track.shape:
            track.shape, track.dtype = list(frame.image.shape), str(frame.image.dtype)
        track.exposure_us = frame.exposure_us
        self._last_frame_ns = max(self._last_frame_ns, t_ns)

    def _pull_robot(self, out: Any, until_ns: int) -> None:
        history = self._history()
        if history is None or self._robot_from_ns is None or until_ns <= self._robot_from_ns:
            return
        t_host, t_robot, T, q = history.columns_between(self._robot_from_ns + 1, until_ns)
        if t_host.size == 0:
            return
        pose = np.column_stack([T[:, :3, 3], rotvec_from_T(T)])
        writer = csv.writer(out)
        for i in range(t_host.size):
            t_r = "" if np.isnan(t_robot[i]) else f"{t_robot[i]:.6f}"
            writer.writerow((int(t_host[i]), t_r, *(f"{x:.6f}" for x in pose[i]), *(f"{x:.8f}" for x in q[i])))
        self.robot_samples += int(t_host.size)
        self._robot_from_ns = int(t_host[-1])

    def _check_disk(self) -> None:
        free = shutil.disk_usage(self.folder).free
        if free < self._min_free and not self._stopping.is_set():
            self.stop(
                f"stopped: {free / 2**20:.0f} MiB left on the disk (the recording keeps {self._min_free / 2**20:.0f})"
            )

    def _finish(self, final: str) -> None:
        """The cameras released, then the final state shown and written, then the recording ended."""
        self._release(self)
        self.state = final
        try:
            fsync_dir(self.folder)
            write_json_atomic(self.folder / MANIFEST, self.summary())
        except OSError as e:
            log.error("recording %s: its manifest could not be written: %s", self.id, e)
        self._on_end(self)


class Recordings:
    """The recordings of one service: started on its cameras, listed from its folder, stopped, deleted."""

    def __init__(
        self,
        root: Path,
        cameras: Mapping[str, Tappable],
        history: Callable[[], RobotHistory | None],
        on_event: Callable[[str, str, str], None],
        min_free_bytes: int = MIN_FREE_BYTES,
        describe: Callable[[], dict[str, Any]] = dict,
    ) -> None:
        self.root, self._cameras, self._history, self._event = root, cameras, history, on_event
        self._describe = describe  # the settings a faithful replay needs (the stated latencies), into the manifest
        self.min_free_bytes = min_free_bytes
        self._active: dict[str, Recording] = {}
        self._lock = threading.Lock()
        self._mark_interrupted()

    def start(self, request: RecordingRequest) -> dict[str, Any]:
        req = request.check(sorted(self._cameras))
        with self._lock:
            busy = [c for r in self._active.values() for c in r.request.cameras if c in req.cameras]
            if busy:
                raise RecordingError("busy", f"camera {busy[0]} is being recorded already; stop that recording first")
            try:
                self.root.mkdir(parents=True, exist_ok=True)
                free = shutil.disk_usage(self.root).free
            except OSError as e:
                raise RecordingError("storage", f"the recordings folder {self.root} cannot be used: {e}") from None
            if free < self.min_free_bytes:
                raise RecordingError(
                    "storage",
                    f"only {free / 2**20:.0f} MiB free at {self.root}; a recording needs more than "
                    f"{self.min_free_bytes / 2**20:.0f} MiB",
                )
            rec_id = self._new_id()
            rec = Recording(
                rec_id, self.root / rec_id, req, self._history, self.min_free_bytes, self._release, self._ended
            )
            rec.settings = self._describe()
            try:
                rec.start()
            except OSError as e:
                rec.close_files()
                shutil.rmtree(self.root / rec_id, ignore_errors=True)
                raise RecordingError("storage", f"the recording could not be started: {e}") from None
            self._active[rec_id] = rec
            for name in req.cameras:
                self._cameras[name].tap = lambda frame, name=name, rec=rec: rec.offer(name, frame)
        self._event("info", "recording_started", f"recording {rec_id} of {', '.join(req.cameras)} started")
        return rec.summary()

    def stop(self, rec_id: str, timeout_s: float = 10.0) -> dict[str, Any]:
        rec = self._active.get(rec_id)
        if rec is None:
            return self.get(rec_id)  # ended already: as it ended
        rec.stop()
        rec.join(timeout_s)
        return rec.summary()

    def get(self, rec_id: str) -> dict[str, Any]:
        rec = self._active.get(rec_id)
        if rec is not None:
            return rec.summary()
        return self._read(rec_id)

    def list(self) -> list[dict[str, Any]]:
        """Every recording, newest first."""
        if not self.root.is_dir():
            return []
        ids = sorted((p.name for p in self.root.iterdir() if _ID.match(p.name)), reverse=True)
        out = []
        for rec_id in ids:
            try:
                out.append(self.get(rec_id))
            except RecordingError:
                continue
        return out

    def delete(self, rec_id: str) -> None:
        if rec_id in self._active:
            raise RecordingError("busy", f"recording {rec_id} is running; stop it first")
        self._read(rec_id)  # not_found when there is none
        shutil.rmtree(self.root / rec_id)
        self._event("info", "recording_deleted", f"recording {rec_id} deleted")

    def close(self) -> None:
        """Stop every running recording (the service stops): each is written to its end."""
        for rec in list(self._active.values()):
            rec.stop("stopped: the service stopped")
            rec.join(10.0)

    # --- internals ------------------------------------------------------------------------------

    def _release(self, rec: Recording) -> None:
        with self._lock:
            for name in rec.request.cameras:
                self._cameras[name].tap = None

    def _ended(self, rec: Recording) -> None:
        with self._lock:
            self._active.pop(rec.id, None)
        frames = sum(t.written for t in rec.tracks.values())
        dropped = sum(t.dropped for t in rec.tracks.values())
        level = "error" if rec.state == "failed" else "info"
        more = f": {rec.message}" if rec.message else ""
        self._event(level, f"recording_{rec.state}", f"recording {rec.id}: {frames} frames, {dropped} dropped{more}")

    def _new_id(self) -> str:
        base = datetime.now(UTC).strftime("%Y%m%d-%H%M%S")
        rec_id, n = base, 1
        while (self.root / rec_id).exists():
            n += 1
            rec_id = f"{base}-{n}"
        return rec_id

    def _read(self, rec_id: str) -> dict[str, Any]:
        if not _ID.match(rec_id):
            raise RecordingError("not_found", f"no recording {rec_id!r}")
        path = self.root / rec_id / MANIFEST
        try:
            data: dict[str, Any] = json.loads(path.read_text(encoding="utf-8"))
        except FileNotFoundError:
            raise RecordingError("not_found", f"no recording {rec_id!r}") from None
        except (OSError, ValueError) as e:
            raise RecordingError("storage", f"recording {rec_id}'s manifest cannot be read: {e}") from None
        return data

    def _mark_interrupted(self) -> None:
        """Recordings a stop cut short (still ``recording`` on disk): counted from their files, marked."""
        for summary in self.list():
            if summary.get("state") != "recording":
                continue
            folder = self.root / summary["id"]
            for name, cam in summary.get("cameras", {}).items():
                cam["written"] = sum(1 for p in (folder / name).glob("frame-*") if p.is_file())
            summary["state"] = "interrupted"
            summary["message"] = "the service stopped while it recorded; the frames written are kept"
            try:
                write_json_atomic(folder / MANIFEST, summary)
            except OSError as e:
                log.error("recording %s could not be marked interrupted: %s", summary["id"], e)
