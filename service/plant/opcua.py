"""The OPC UA server for the cell's PLC: the newest result per camera, device states, ``Measure``.

The server (``asyncua``) runs in a thread of its own with its own event loop: a PLC's sessions,
subscriptions and method calls never compete with the HTTP API's loop, and the measurement
thread never waits for them. Every ``update_rate_hz`` the server's loop takes the worker's newest
result of each camera (``Worker.current``: stale results are marked as such) and its health, and
writes the variables that changed, so that a burst of frames costs the PLC side nothing extra.

Address space (namespace ``namespace_uri``; string node ids ``Posecell.<path>``, stable for PLC
programs that address nodes by id)::

    Objects/Posecell
        VisionState        String   Operational | Preoperational | Error (OPC 40100's top states)
        Ready, Busy, ResultValid, Fault  Boolean   the PLC handshake of vision systems
        FaultCode Int32, FaultMessage String       0 = none; FAULT_CODES below
        RobotState         String
        Measure(Camera String, Timeout_s Double) -> ResultOk, Reason, Message, ResultSeq,
                MeasurementId, DeviationPosition_mm, DeviationAngle_deg, T_base_flange_measured,
                ExposureTime
        StartTest(Kind String, Parameters String) -> Ok, Reason, Message, TestId, Status
        StopTest(TestId Int64) -> Ok, Reason, Message, Status      (the accuracy tests, as /tests)
        StartRecording(Parameters String) -> Ok, Reason, Message, RecordingId, State
        StopRecording(RecordingId String) -> Ok, Reason, Message, State  (recordings, as /recordings)
        Cameras/<camera>
            ResultSeq Int64 (frame number, -1: none), ResultOk Boolean, Reason String,
            Message String, T_base_flange_measured Double[16] (row-major, mm), DeviationPosition_mm
            Double, DeviationAngle_deg Double, SigmaPosition_mm Double[3], ExposureTime DateTime
            (mid-exposure, UTC), CameraState String

A value that a result does not have (no flange pose, an outage) is NaN, with ``ResultOk`` false
and ``Reason`` saying why. The handshake: ``Measure`` sets ``Busy`` and clears ``ResultValid``;
on return ``ResultValid`` is true when the result is a pose committed to the database (the REST
API's acknowledgement). ``Ready`` is the health status ``ok`` while not busy; ``Fault`` and
``FaultCode`` come from the device and storage states.

Security: anonymous sessions may browse, read and subscribe; writes and method calls need the
user ``posecell`` with the API token as password (``_Users``, ``_Permissions``); a wrong password
is refused when the session is activated. Endpoints: security policy None (anyone may read) and
Basic256Sha256 SignAndEncrypt; the server's key and self-signed certificate live in
``<state_dir>/opcua/`` (made at the first start, the certificate renewed when invalid), and with
them the password is encrypted with the server's key even on the None endpoint. Client
certificates are not checked: the user and password decide, not the certificate.
"""

from __future__ import annotations

import asyncio
import hmac
import json
import logging
import math
import os
import socket
import threading
import time
from collections.abc import Callable, Mapping
from datetime import UTC, datetime
from pathlib import Path
from typing import Any
from urllib.parse import urlsplit

from asyncua import Server, ua
from asyncua.crypto import cert_gen
from asyncua.crypto.permission_rules import USER_TYPES, PermissionRuleset, User, UserRole
from cryptography.x509.oid import ExtendedKeyUsageOID

from service.core.measurement import Measurement
from service.core.results import Failure, Reason
from service.runtime.recorder import RecordingError, RecordingRequest
from service.runtime.rig_combiner import RIG
from service.runtime.worker import Worker
from service.settings import OpcUaConfig

log = logging.getLogger(__name__)

USER = "posecell"
STOP_TIMEOUT_S = 10.0
HEALTH_RATE_HZ = 5.0  # device states and faults reach the PLC within 0.2 s (plus one update period)
NO_TIME = datetime(1601, 1, 1, tzinfo=UTC)  # OPC UA's null DateTime: no exposure (an outage)
NAN16 = [math.nan] * 16
# FaultCode values: stable numbers, so that a PLC program may switch on them
FAULT_CODES = {
    None: 0,
    Reason.camera_disconnected: 1,
    Reason.robot_disconnected: 2,
    Reason.storage_unavailable: 3,
    Reason.not_calibrated: 4,
    Reason.initializing: 5,
}
VISION_STATES = {"ok": "Operational", "initializing": "Preoperational", "degraded": "Error"}
# a result that says the cell could not measure at all: answered without waiting for storage
_DEVICE_REASONS = {Reason.camera_disconnected, Reason.initializing, Reason.not_calibrated, Reason.stale}
_WRITE_AND_CALL = {
    ua.NodeId(ua.ObjectIds.WriteRequest_Encoding_DefaultBinary),
    ua.NodeId(ua.ObjectIds.CallRequest_Encoding_DefaultBinary),
    ua.NodeId(ua.ObjectIds.HistoryUpdateRequest_Encoding_DefaultBinary),
}
V = ua.VariantType


class _Users:
    """asyncua's user manager: anonymous, or ``posecell`` + the API token; anyone else is refused."""

    def __init__(self, token: str) -> None:
        self._token = token.encode()

    def get_user(self, iserver: Any, username: str | None = None, password: Any = None, certificate: Any = None) -> Any:
        if username is None:  # an anonymous token (certificate tokens are not offered)
            return User(role=UserRole.Anonymous)
        given = password.encode() if isinstance(password, str) else (password or b"")
        if username == USER and self._token and hmac.compare_digest(given, self._token):
            return User(role=UserRole.User, name=USER)
        return None  # the session is not activated: BadUserAccessDenied


class _Permissions(PermissionRuleset):
    """Users may do what asyncua's users may; anonymous sessions the same, less writes and calls."""

    def __init__(self) -> None:
        user = {ua.NodeId(t) for t in USER_TYPES}
        self._allowed = {UserRole.User: user, UserRole.Anonymous: user - _WRITE_AND_CALL, UserRole.Admin: user}

    def check_validity(self, user: Any, action_type_id: Any, body: Any) -> bool:
        return action_type_id in self._allowed.get(user.role, set())


def _arg(name: str, vtype: ua.VariantType, description: str, length: int = 0) -> ua.Argument:
    a = ua.Argument()
    a.Name = name
    a.DataType = ua.NodeId(vtype.value)
    a.ValueRank = 1 if length else -1
    a.ArrayDimensions = [length] if length else []
    a.Description = ua.LocalizedText(description)
    return a


CAMERA_VARIABLES: tuple[tuple[str, ua.VariantType, Any], ...] = (
    ("ResultSeq", V.Int64, -1),
    ("ResultOk", V.Boolean, False),
    ("Reason", V.String, "no_frame"),
    ("Message", V.String, "no frame has been measured yet"),
    ("T_base_flange_measured", V.Double, NAN16),
    ("DeviationPosition_mm", V.Double, math.nan),
    ("DeviationAngle_deg", V.Double, math.nan),
    ("SigmaPosition_mm", V.Double, [math.nan] * 3),
    ("ExposureTime", V.DateTime, NO_TIME),
    ("CameraState", V.String, "starting"),
)
CELL_VARIABLES: tuple[tuple[str, ua.VariantType, Any], ...] = (
    ("VisionState", V.String, "Preoperational"),
    ("Ready", V.Boolean, False),
    ("Busy", V.Boolean, False),
    ("ResultValid", V.Boolean, False),
    ("Fault", V.Boolean, False),
    ("FaultCode", V.Int32, 0),
    ("FaultMessage", V.String, ""),
    ("RobotState", V.String, "starting"),
)
MEASURE_OUTPUTS = (
    _arg("ResultOk", V.Boolean, "a pose was measured and committed to the database"),
    _arg("Reason", V.String, "why not (DESIGN section 4 reasons); empty when ok"),
    _arg("Message", V.String, "the reason as a sentence"),
    _arg("ResultSeq", V.Int64, "the camera's frame number; -1: none"),
    _arg("MeasurementId", V.Int64, "the database row of the result; -1: not stored"),
    _arg("DeviationPosition_mm", V.Double, "measured minus reported flange position, mm"),
    _arg("DeviationAngle_deg", V.Double, "measured minus reported flange orientation, deg"),
    _arg("T_base_flange_measured", V.Double, "measured flange pose in base, 4x4 row-major, mm", 16),
    _arg("ExposureTime", V.DateTime, "mid-exposure instant, UTC"),
)

_TEST_OUTCOME = (
    _arg("Ok", V.Boolean, "the runner accepted the request"),
    _arg("Reason", V.String, "why not (busy, not_calibrated, bad_input, not_found, ...); empty when ok"),
    _arg("Message", V.String, "the reason as a sentence"),
)
START_TEST_INPUTS = [
    _arg("Kind", V.String, "circle (ISO 230-4) | iso9283 (ISO 9283 poses) | table1 (the paper's Table 1)"),
    _arg("Parameters", V.String, 'the parameters as a JSON object (POST /tests/{kind}), e.g. {"mode": "record"}'),
]
START_TEST_OUTPUTS = [
    *_TEST_OUTCOME,
    _arg("TestId", V.Int64, "the test's id (GET /tests/{id}); -1: none"),
    _arg("Status", V.String, "queued | running | ..."),
]
STOP_TEST_INPUTS = [_arg("TestId", V.Int64, "the test to finish (record mode) or cancel (program mode)")]
STOP_TEST_OUTPUTS = [*_TEST_OUTCOME, _arg("Status", V.String, "the test's status after the stop")]
START_RECORDING_INPUTS = [
    _arg("Parameters", V.String, 'POST /recordings\'s body as JSON, e.g. {"max_frames": 200}; empty: the defaults'),
]
START_RECORDING_OUTPUTS = [
    *_TEST_OUTCOME,
    _arg("RecordingId", V.String, "the recording's id (GET /recordings/{id}); empty: none"),
    _arg("State", V.String, "recording | complete | stopped | failed"),
]
STOP_RECORDING_INPUTS = [_arg("RecordingId", V.String, "the recording to end now")]
STOP_RECORDING_OUTPUTS = [*_TEST_OUTCOME, _arg("State", V.String, "the recording's state after the stop")]


def result_values(m: Measurement | None) -> dict[str, Any]:
    """A camera's variables from its newest result (NaN where the result has no such value)."""
    if m is None:
        return {name: default for name, _, default in CAMERA_VARIABLES if name != "CameraState"}
    flange = m.flange
    dev = flange.deviation if flange is not None else None
    T = flange.T_base_flange_measured if flange is not None else None
    sigma = None if isinstance(m.result, Failure) else m.result.sigma_position_mm
    t_exp = m.t_exposure_unix_ns
    return {
        "ResultSeq": -1 if m.seq is None else int(m.seq),
        "ResultOk": bool(m.ok),
        "Reason": "" if m.ok else str(m.reason or ""),
        "Message": m.message,
        "T_base_flange_measured": NAN16 if T is None else [float(v) for v in T.reshape(16)],
        "DeviationPosition_mm": math.nan if dev is None else float(dev.position_mm),
        "DeviationAngle_deg": math.nan if dev is None else float(dev.angle_deg),
        "SigmaPosition_mm": [math.nan] * 3 if sigma is None else [float(v) for v in sigma],
        "ExposureTime": NO_TIME if t_exp is None else datetime.fromtimestamp(t_exp / 1e9, UTC),
    }


def fault_of(health: Mapping[str, Any]) -> tuple[Reason | None, str]:
    """The cell's fault from its ``/health`` document: the first of storage, cameras, robot, calibration."""
    problems = list(health.get("problems") or ())
    storage = health.get("storage") or {}
    if storage and storage.get("state") not in (None, "ok"):
        return Reason.storage_unavailable, storage.get("error") or "the database does not accept writes"
    for name, cam in (health.get("cameras") or {}).items():
        if cam.get("state") not in ("ok", "starting"):
            return Reason.camera_disconnected, f"camera {name}: {cam.get('error') or cam.get('state')}"
    robot = health.get("robot") or {}
    if robot.get("state") not in (None, "ok", "starting", "absent"):
        return Reason.robot_disconnected, f"robot: {robot.get('error') or robot.get('state')}"
    calibration = health.get("calibration") or {}
    missing = [k for k in ("camera", "field", "handeye") if k in calibration and not calibration[k].get("present")]
    if missing:
        return Reason.not_calibrated, f"not calibrated: no {', no '.join(missing)} calibration"
    if health.get("status") == "initializing":
        return Reason.initializing, "the service is starting"
    return (None, "") if not problems else (None, "; ".join(problems))


class OpcUaServer:
    """The OPC UA server of one cell (see the module docstring); ``start`` returns at once."""

    def __init__(
        self,
        config: OpcUaConfig,
        worker: Worker,
        token: str,
        health: Callable[[], Mapping[str, Any]],
        tests: Callable[[], Any] = lambda: None,
        cert_dir: Path | None = None,
        recordings: Callable[[], Any] = lambda: None,
    ) -> None:
        self.config = config
        self._cert_dir = cert_dir  # the server's key and self-signed certificate; None: none (password in clear)
        self._worker = worker
        self._tests = tests  # the accuracy tests' runner (start(kind, params), stop(id)), once it is up
        self._recordings = recordings  # the recordings (start(request), stop(id)), once they are up
        self._token = token
        self._health = health
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()  # looked at every update period, also before the server is up
        self._state = "stopped"
        self._last_error = ""
        self._busy = 0
        self._nodes: dict[str, tuple[ua.NodeId, ua.VariantType]] = {}
        self._written: dict[str, Any] = {}
        self._server: Server | None = None
        self.counters = {"updates": 0, "measure_calls": 0}
        self._health_doc: dict[str, Any] | None = None
        self._next_health = 0.0

    # --- life cycle --------------------------------------------------------------------------------

    def start(self) -> None:
        self._state = "starting"
        self._thread = threading.Thread(target=self._thread_main, name="opcua-server", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(STOP_TIMEOUT_S)
            if self._thread.is_alive():
                log.warning("the OPC UA server did not stop within %.0f s; left behind", STOP_TIMEOUT_S)
            self._thread = None

    def stats(self) -> dict[str, Any]:
        """The ``opcua`` section of ``/health``."""
        return {"state": self._state, "endpoint": self.config.endpoint, **self.counters, "last_error": self._last_error}

    def _thread_main(self) -> None:
        try:
            asyncio.run(self._main())
        except Exception as e:  # a port in use, a bad host: reported in /health, the cell measures on
            self._state = "failed"
            self._last_error = f"the OPC UA server on {self.config.endpoint} could not run: {e}"
            log.error("%s", self._last_error)

    async def _main(self) -> None:
        server = Server(user_manager=_Users(self._token))
        await server.init()
        server.set_endpoint(self.config.endpoint)
        server.set_server_name("posecell")
        await server.set_application_uri(self.config.namespace_uri)
        policies = [ua.SecurityPolicyType.NoSecurity]
        if self._cert_dir is not None:
            await self._load_certificate(server)
            # a SignAndEncrypt endpoint besides None: asyncua then encrypts the user token (the password)
            # with the server's key on the None endpoint too
            policies.append(ua.SecurityPolicyType.Basic256Sha256_SignAndEncrypt)
        server.set_security_policy(policies, permission_ruleset=_Permissions())
        server.set_identity_tokens([ua.AnonymousIdentityToken, ua.UserNameIdentityToken])
        await self._build(server, await server.register_namespace(self.config.namespace_uri))
        self._server = server
        async with server:  # start ... stop
            self._state = "running"
            log.info("OPC UA server on %s", self.config.endpoint)
            period_s = 1.0 / self.config.update_rate_hz
            while not self._stop.is_set():
                t0 = time.monotonic()
                try:
                    await self._update()
                except Exception:
                    log.exception("the OPC UA variables could not be updated")
                await asyncio.sleep(max(0.0, period_s - (time.monotonic() - t0)))
        self._state = "stopped"

    async def _load_certificate(self, server: Server) -> None:
        """The server's RSA key (made once, mode 0600) and its self-signed certificate (renewed yearly)."""
        assert self._cert_dir is not None
        self._cert_dir.mkdir(parents=True, exist_ok=True)
        key_file, cert_file = self._cert_dir / "server-key.pem", self._cert_dir / "server-cert.der"
        if not key_file.exists():
            fd = os.open(key_file, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
            with os.fdopen(fd, "wb") as f:
                f.write(cert_gen.dump_private_key_as_pem(cert_gen.generate_private_key()))
        host = urlsplit(self.config.endpoint).hostname or socket.gethostname()
        await cert_gen.setup_self_signed_certificate(
            key_file,
            cert_file,
            self.config.namespace_uri,
            host,
            [ExtendedKeyUsageOID.SERVER_AUTH],
            {"commonName": f"posecell {host}", "organizationName": "posecell"},
        )
        await server.load_certificate(str(cert_file))
        await server.load_private_key(str(key_file))

    # --- the address space -------------------------------------------------------------------------

    async def _build(self, server: Server, ns: int) -> None:
        cell = await server.nodes.objects.add_object(ua.NodeId("Posecell", ns), ua.QualifiedName("Posecell", ns))
        for name, vtype, default in CELL_VARIABLES:
            await self._variable(cell, ns, f"Posecell.{name}", name, vtype, default)
        inputs = [
            _arg(
                "Camera", V.String, "camera name, or empty: the first result of all cameras (the rig's when calibrated)"
            ),
            _arg("Timeout_s", V.Double, "longest wait for the next frame, s, (0, 30]; 0: 2 s"),
        ]
        await cell.add_method(
            ua.NodeId("Posecell.Measure", ns), ua.QualifiedName("Measure", ns), self._measure, inputs, MEASURE_OUTPUTS
        )
        for name, func, ins, outs in (
            ("StartTest", self._start_test, START_TEST_INPUTS, START_TEST_OUTPUTS),
            ("StopTest", self._stop_test, STOP_TEST_INPUTS, STOP_TEST_OUTPUTS),
            ("StartRecording", self._start_recording, START_RECORDING_INPUTS, START_RECORDING_OUTPUTS),
            ("StopRecording", self._stop_recording, STOP_RECORDING_INPUTS, STOP_RECORDING_OUTPUTS),
        ):
            await cell.add_method(ua.NodeId(f"Posecell.{name}", ns), ua.QualifiedName(name, ns), func, ins, outs)
        cameras = await cell.add_folder(ua.NodeId("Posecell.Cameras", ns), ua.QualifiedName("Cameras", ns))
        for camera in self._cameras():
            obj = await cameras.add_object(ua.NodeId(f"Posecell.Cameras.{camera}", ns), ua.QualifiedName(camera, ns))
            for name, vtype, default in CAMERA_VARIABLES:
                await self._variable(obj, ns, f"Posecell.Cameras.{camera}.{name}", name, vtype, default)

    async def _variable(self, parent: Any, ns: int, node_id: str, name: str, vtype: ua.VariantType, value: Any) -> None:
        node = await parent.add_variable(ua.NodeId(node_id, ns), ua.QualifiedName(name, ns), value, varianttype=vtype)
        if isinstance(value, list):
            await node.write_value_rank(1)
            await node.write_array_dimensions([len(value)])
        self._nodes[node_id] = (node.nodeid, vtype)
        self._written[node_id] = value

    def _cameras(self) -> list[str]:
        # two or more cameras may be combined into the rig's results (once a rig is calibrated)
        names = list(self._worker.processors)
        return [*names, RIG] if len(names) > 1 else names

    async def _write(self, values: Mapping[str, Any]) -> None:
        """Write the values that changed (a PLC subscribed to them hears of real changes only)."""
        assert self._server is not None
        for node_id, value in values.items():
            if _same(self._written.get(node_id), value):
                continue
            nodeid, vtype = self._nodes[node_id]
            await self._server.write_attribute_value(nodeid, ua.DataValue(ua.Variant(value, vtype)))
            self._written[node_id] = value

    async def _update(self) -> None:
        # worker.health() and current() take the worker's lock briefly and never wait on a device;
        # the health document (medians, the store's state) is built at most HEALTH_RATE_HZ
        now = time.monotonic()
        if self._health_doc is None or now >= self._next_health:
            self._health_doc, self._next_health = dict(self._health()), now + 1.0 / HEALTH_RATE_HZ
        health = self._health_doc
        values: dict[str, Any] = {}
        cams = health.get("cameras") or {}
        for camera in self._cameras():
            prefix = f"Posecell.Cameras.{camera}."
            values.update({prefix + k: v for k, v in result_values(self._worker.current(camera)).items()})
            values[prefix + "CameraState"] = str((cams.get(camera) or {}).get("state", "ok"))
        reason, message = fault_of(health)
        status = str(health.get("status", "initializing"))
        values.update(
            {
                "Posecell.VisionState": VISION_STATES.get(status, "Error"),
                "Posecell.Ready": status == "ok" and self._busy == 0,
                "Posecell.Busy": self._busy > 0,
                "Posecell.Fault": reason not in (None, Reason.initializing),
                "Posecell.FaultCode": FAULT_CODES.get(reason, 99),
                "Posecell.FaultMessage": message,
                "Posecell.RobotState": str((health.get("robot") or {}).get("state", "absent")),
            }
        )
        await self._write(values)
        self.counters["updates"] += 1

    # --- Measure -----------------------------------------------------------------------------------

    async def _measure(self, parent: Any, *args: Any) -> Any:
        camera = str(args[0].Value or "") if args else ""
        timeout_s = float(args[1].Value or 2.0) if len(args) > 1 else 2.0
        if camera and camera not in self._cameras():
            return ua.StatusCode(ua.StatusCodes.BadInvalidArgument)
        if not (0 < timeout_s <= 30) or not math.isfinite(timeout_s):
            return ua.StatusCode(ua.StatusCodes.BadOutOfRange)
        self.counters["measure_calls"] += 1
        self._busy += 1
        await self._write({"Posecell.Busy": True, "Posecell.Ready": False, "Posecell.ResultValid": False})
        try:
            out = await self._measure_once(camera or None, timeout_s)
        finally:
            self._busy -= 1
        await self._write({"Posecell.Busy": self._busy > 0, "Posecell.ResultValid": bool(out[0])})
        types = [V.Boolean, V.String, V.String, V.Int64, V.Int64, V.Double, V.Double, V.Double, V.DateTime]
        return [ua.Variant(v, t) for v, t in zip(out, types, strict=True)]

    async def _measure_once(self, camera: str | None, timeout_s: float) -> list[Any]:
        """``POST /measure``'s path: the next frame's result, acknowledged once committed."""
        deadline = time.monotonic() + timeout_s
        fut = self._worker.request_measurement(camera)
        try:
            answer = await asyncio.wait_for(asyncio.wrap_future(fut), timeout_s)
        except TimeoutError:
            fut.cancel()
            return _outputs(None, str(Reason.timeout), f"no frame was measured within {timeout_s} s", -1)
        result = answer.result
        if not result.ok and result.reason in _DEVICE_REASONS:
            return _outputs(result, str(result.reason), result.message, -1)
        stored, why = await asyncio.to_thread(self._worker.wait_stored, answer, deadline - time.monotonic())
        if not stored:
            return _outputs(result, str(Reason.storage_unavailable), why, -1, ok=False)
        seq = -1 if answer.stored_seq is None else int(answer.stored_seq)
        return _outputs(result, "" if result.ok else str(result.reason), result.message, seq)

    # --- the accuracy tests (GET/POST /tests's runner) ---------------------------------------------

    async def _start_test(self, parent: Any, *args: Any) -> Any:
        kind = str(args[0].Value or "") if args else ""
        text = str(args[1].Value or "") if len(args) > 1 else ""
        try:
            params = json.loads(text) if text.strip() else {}
        except ValueError as e:
            return _test_outputs(False, str(Reason.bad_input), f"Parameters is not JSON: {e}", -1, "")
        if not isinstance(params, dict):
            return _test_outputs(False, str(Reason.bad_input), "Parameters must be a JSON object", -1, "")
        done = await self._call_tests("start", kind, params)
        if isinstance(done, tuple):
            return _test_outputs(False, *done, -1, "")
        return _test_outputs(True, "", "", int(done["id"]), str(done.get("status", "")))

    async def _stop_test(self, parent: Any, *args: Any) -> Any:
        test_id = int(args[0].Value or 0) if args else 0
        done = await self._call_tests("stop", test_id)
        if isinstance(done, tuple):
            return _test_outputs(False, *done, None, "")
        return _test_outputs(True, "", str(done.get("error") or ""), None, str(done.get("status", "")))

    async def _call_tests(self, method: str, *args: Any) -> dict[str, Any] | tuple[str, str]:
        """The runner's answer, or ``(reason, message)`` of its refusal (a failure as a value)."""
        tests = self._tests()
        if tests is None:
            return str(Reason.initializing), "the accuracy tests are not available (yet)"
        try:
            # start writes the test's row, stop waits for the test's thread: both off this loop
            answer: dict[str, Any] = await asyncio.to_thread(getattr(tests, method), *args)
        except Exception as e:
            reason = getattr(e, "reason", None)  # the runner's TestError; anything else is a bug: raised
            if reason is None:
                raise
            return str(reason), str(getattr(e, "message", e))
        return answer

    # --- recordings (POST /recordings's) ------------------------------------------------------------

    async def _start_recording(self, parent: Any, *args: Any) -> Any:
        text = str(args[0].Value or "") if args else ""
        try:
            params = json.loads(text) if text.strip() else {}
            if not isinstance(params, dict):
                raise ValueError("not a JSON object")
            request = RecordingRequest.from_dict(params)
        except ValueError as e:
            return _recording_outputs(False, str(Reason.bad_input), f"Parameters must be a JSON object: {e}", "", "")
        except RecordingError as e:
            return _recording_outputs(False, str(e.reason), e.message, "", "")
        done = await self._call_recordings("start", request)
        if isinstance(done, tuple):
            return _recording_outputs(False, *done, "", "")
        return _recording_outputs(True, "", "", str(done["id"]), str(done["state"]))

    async def _stop_recording(self, parent: Any, *args: Any) -> Any:
        rec_id = str(args[0].Value or "") if args else ""
        done = await self._call_recordings("stop", rec_id)
        if isinstance(done, tuple):
            return _recording_outputs(False, *done, None, "")
        return _recording_outputs(True, "", str(done.get("message") or ""), None, str(done["state"]))

    async def _call_recordings(self, method: str, *args: Any) -> dict[str, Any] | tuple[str, str]:
        recordings = self._recordings()
        if recordings is None:
            return str(Reason.initializing), "the recordings are not available (yet)"
        try:  # start makes folders, stop waits for the writer: both off this loop
            answer: dict[str, Any] = await asyncio.to_thread(getattr(recordings, method), *args)
        except RecordingError as e:
            return str(e.reason), e.message
        return answer


def _outcome(ok: bool, reason: str, message: str, ident: ua.Variant | None, state: str) -> list[Any]:
    """A request method's outputs: Ok, Reason, Message, the test's or recording's id (only where the
    method returns one), its status."""
    values = [ua.Variant(ok, V.Boolean), ua.Variant(reason, V.String), ua.Variant(message, V.String)]
    if ident is not None:
        values.append(ident)
    return [*values, ua.Variant(state, V.String)]


def _recording_outputs(ok: bool, reason: str, message: str, rec_id: str | None, state: str) -> list[Any]:
    return _outcome(ok, reason, message, None if rec_id is None else ua.Variant(rec_id, V.String), state)


def _test_outputs(ok: bool, reason: str, message: str, test_id: int | None, status: str) -> list[Any]:
    return _outcome(ok, reason, message, None if test_id is None else ua.Variant(test_id, V.Int64), status)


def _outputs(
    m: Measurement | None, reason: str, message: str, measurement_id: int, ok: bool | None = None
) -> list[Any]:
    v = result_values(m)
    return [
        bool(m is not None and m.ok) if ok is None else ok,
        reason,
        message,
        v["ResultSeq"],
        measurement_id,
        v["DeviationPosition_mm"],
        v["DeviationAngle_deg"],
        v["T_base_flange_measured"],
        v["ExposureTime"],
    ]


def _same(a: Any, b: Any) -> bool:
    # NaN != NaN: an unchanged "no value" must not be written ten times a second
    if isinstance(a, float) and isinstance(b, float):
        return a == b or (math.isnan(a) and math.isnan(b))
    if isinstance(a, list) and isinstance(b, list):
        return len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b, strict=True))
    return bool(a == b)
