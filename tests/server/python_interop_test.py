"""Interop: a Python client built only from Debian's python3-grpcio and the
stubs our proto generates (system protoc + grpc_python_plugin) talks to the
real framediffuser-server binary: lists environments, checks health and
reflection, opens a session and renders frames, then stops the server with
SIGTERM and watches it drain. With a model repository, a real SIGHUP reloads
a changed environment and reports a corrupt one, while a session streams.

Usage (ctest runs it so): python3 python_interop_test.py SERVER_BINARY
with PYTHONPATH holding the generated stubs (build/<dir>/python).
"""
import importlib.util
import json
import os
import queue
import re
import secrets
import shutil
import signal
import struct
import subprocess
import sys
import tempfile
import threading
import unittest

import grpc
from framediffuser.v1 import image_pb2, render_service_pb2, render_service_pb2_grpc

# The stubs of grpc/health/v1/health.proto live in the generated "grpc"
# folder, but "grpc" is python3-grpcio's (regular) package, which ships no
# health module: extend its search path with the generated folder so that
# health_pb2_grpc's own "from grpc.health.v1 import health_pb2" works too.
for _entry in os.environ.get("PYTHONPATH", "").split(os.pathsep):
    if _entry and os.path.isdir(os.path.join(_entry, "grpc", "health", "v1")):
        grpc.__path__.append(os.path.join(_entry, "grpc"))
from grpc.health.v1 import health_pb2, health_pb2_grpc  # noqa: E402

SERVER_BINARY = None  # set by main() from argv
SERVICE = "framediffuser.v1.FrameDiffuser"
# Bounds a hung server instead of hanging ctest; not a timing assertion.
RPC_TIMEOUT_S = 300
SIZE = 64
# The shipped environments (the repository's environments/ folder).
ENVIRONMENTS_DIR = os.path.normpath(os.path.join(os.path.dirname(os.path.abspath(__file__)),
                                                 "..", "..", "environments"))

zstandard = (importlib.import_module("zstandard")
             if importlib.util.find_spec("zstandard") is not None else None)


class ServerProcess:
    """The real binary on an ephemeral port. Its stderr is read line by line
    (blocking reads) until the listening line, then drained by a thread so
    that the pipe never fills; every line is kept for the log checks."""

    def __init__(self, extra_args=()):
        args = [SERVER_BINARY, "--listen", "127.0.0.1:0", "--max_steps", "10",
                "--log_format", "json", "--threads", "1", *extra_args]
        self.proc = subprocess.Popen(args, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                                     stderr=subprocess.PIPE, text=True, errors="replace")
        self.lines = []
        self.port = None
        for line in iter(self.proc.stderr.readline, ""):
            self.lines.append(line.rstrip("\n"))
            match = re.search(r"framediffuser-server listening on port (\d+)", line)
            if match:
                self.port = int(match.group(1))
                break
        if self.port is None:
            code = self.proc.wait()
            raise AssertionError("server exited (code %s) before listening; stderr:\n%s" %
                                 (code, "\n".join(self.lines)))
        self.changed = threading.Condition()
        self._drainer = threading.Thread(target=self._drain, daemon=True)
        self._drainer.start()
        self.channel = grpc.insecure_channel("127.0.0.1:%d" % self.port)

    def _drain(self):
        for line in iter(self.proc.stderr.readline, ""):
            with self.changed:
                self.lines.append(line.rstrip("\n"))
                self.changed.notify_all()

    def wait_for_event(self, event, timeout=60):
        """Blocks until a JSON log line with this "event" arrives (a
        condition wait on the stderr reader, not a sleep)."""
        with self.changed:
            return self.changed.wait_for(lambda: event in self.events(), timeout=timeout)

    def wait_for_log(self, predicate, timeout=120):
        """Blocks until predicate(parsed JSON log lines) holds (a condition
        wait on the stderr reader, not a sleep)."""
        with self.changed:
            return self.changed.wait_for(lambda: predicate(self.records()), timeout=timeout)

    def records(self):
        """Every JSON log line, parsed."""
        found = []
        for line in self.lines:
            if line.startswith("{"):
                try:
                    found.append(json.loads(line))
                except json.JSONDecodeError:
                    pass
        return found

    def terminate_and_wait(self):
        """SIGTERM; returns the exit code (waits at most 30 s)."""
        self.proc.send_signal(signal.SIGTERM)
        code = self.proc.wait(timeout=30)
        self._drainer.join()  # EOF once the process is gone
        return code

    def events(self):
        """The "event" of every JSON log line."""
        found = []
        for line in self.lines:
            if line.startswith("{"):
                try:
                    found.append(json.loads(line).get("event"))
                except json.JSONDecodeError:
                    pass
        return found

    def close(self):
        self.channel.close()
        if self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait()
        if self._drainer.is_alive():
            self._drainer.join()
        self.proc.stderr.close()

    def log_text(self):
        return "\n".join(self.lines)


class Requests:
    """A request iterator the test feeds one message at a time, so that it
    can wait for each answer (lock step) and decide when to half-close."""

    _END = object()

    def __init__(self):
        self._queue = queue.Queue()

    def send(self, request):
        self._queue.put(request)

    def half_close(self):
        self._queue.put(self._END)

    def __iter__(self):
        while True:
            item = self._queue.get()
            if item is self._END:
                return
            yield item


def u8_image(channels, salt, width=SIZE, height=SIZE):
    count = width * height * channels
    data = bytes((i * 31 + salt * 7 + (i // (width * channels)) * 3) % 256 for i in range(count))
    return image_pb2.Image(width=width, height=height, channels=channels,
                           dtype=image_pb2.DTYPE_UINT8, data=data)


def frame_request(index, depth_channels=1):
    gbuffer = render_service_pb2.GBuffer(
        basecolor=u8_image(3, index), normals=u8_image(3, index + 1),
        depth=u8_image(depth_channels, index + 2), roughness=u8_image(1, index + 3))
    return render_service_pb2.RenderRequest(
        frame=render_service_pb2.FrameInput(frame_index=index, gbuffer=gbuffer))


def open_request(**fields):
    open_session = render_service_pb2.OpenSession(environment="default", width=SIZE, height=SIZE,
                                                  steps=2, seed=3, **fields)
    return render_service_pb2.RenderRequest(open=open_session)


class InteropTest(unittest.TestCase):

    def setUp(self):
        self.server = ServerProcess()
        self.addCleanup(self.server.close)
        self.stub = render_service_pb2_grpc.FrameDiffuserStub(self.server.channel)

    def assert_rendered(self, response, index, dtype=image_pb2.DTYPE_UINT8,
                        compression=image_pb2.COMPRESSION_NONE):
        self.assertEqual(response.WhichOneof("kind"), "frame", response)
        frame = response.frame
        self.assertEqual(frame.frame_index, index)
        image = frame.image
        self.assertEqual((image.width, image.height, image.channels), (SIZE, SIZE, 3))
        self.assertEqual(image.dtype, dtype)
        self.assertEqual(image.compression, compression)
        return image

    # Steps 2-4: environments, health, reflection.
    def check_discovery(self):
        envs = self.stub.ListEnvironments(render_service_pb2.ListEnvironmentsRequest(),
                                          timeout=RPC_TIMEOUT_S).environments
        self.assertEqual([env.name for env in envs], ["default"])
        env = envs[0]
        self.assertEqual(env.readiness, render_service_pb2.READINESS_READY, env)
        self.assertEqual(env.readiness_detail, "")
        self.assertIn("trained by framediffuser-train", env.description.lower())
        self.assertEqual((env.native_width, env.native_height), (128, 128))
        self.assertEqual(env.default_steps, 1)  # environments/street/environment.json
        self.assertGreaterEqual(env.max_steps, 2)
        self.assertLessEqual(env.min_size, SIZE)
        self.assertGreaterEqual(env.max_size, SIZE)

        health = health_pb2_grpc.HealthStub(self.server.channel)
        for name in ("", SERVICE, SERVICE + "/default"):
            with self.subTest(health_service=name):
                reply = health.Check(health_pb2.HealthCheckRequest(service=name),
                                     timeout=RPC_TIMEOUT_S)
                self.assertEqual(reply.status, health_pb2.HealthCheckResponse.SERVING)
        with self.assertRaises(grpc.RpcError) as unknown:
            health.Check(health_pb2.HealthCheckRequest(service=SERVICE + "/no_such_env"),
                         timeout=RPC_TIMEOUT_S)
        self.assertEqual(unknown.exception.code(), grpc.StatusCode.NOT_FOUND)

        # ServerReflectionRequest{list_services: ""}: field 7, length 0.
        reflection = self.server.channel.stream_stream(
            "/grpc.reflection.v1alpha.ServerReflection/ServerReflectionInfo",
            request_serializer=None, response_deserializer=None)
        answers = list(reflection(iter([b"\x3a\x00"]), timeout=RPC_TIMEOUT_S))
        self.assertEqual(len(answers), 1)
        self.assertIn(SERVICE.encode(), answers[0])
        self.assertIn(b"grpc.health.v1.Health", answers[0])

    # Step 5: a uint8 session with an adopted x-session-id and a bad frame.
    def check_uint8_session(self):
        session_id = secrets.token_hex(16)
        requests = Requests()
        responses = self.stub.Render(iter(requests), metadata=(("x-session-id", session_id),),
                                     timeout=RPC_TIMEOUT_S)
        requests.send(open_request())
        opened = next(responses)
        self.assertEqual(opened.WhichOneof("kind"), "opened", opened)
        self.assertEqual(opened.opened.session_id, session_id)
        self.assertFalse(opened.opened.resumed)
        self.assertTrue(opened.opened.resume_token)
        settings = opened.opened.settings
        self.assertEqual((settings.environment, settings.width, settings.height, settings.seed,
                          settings.steps), ("default", SIZE, SIZE, 3, 2))
        self.assertEqual(settings.output_dtype, image_pb2.DTYPE_UINT8)

        rendered = []
        for index in (1, 2):
            requests.send(frame_request(index))
            rendered.append(self.assert_rendered(next(responses), index))
        # A depth plane with 3 channels: rejected by name, the stream goes
        # on, and the corrected frame may reuse the index.
        requests.send(frame_request(3, depth_channels=3))
        error = next(responses)
        self.assertEqual(error.WhichOneof("kind"), "frame_error", error)
        self.assertEqual(error.frame_error.frame_index, 3)
        self.assertEqual(error.frame_error.code, grpc.StatusCode.INVALID_ARGUMENT.value[0])
        self.assertIn("frame.gbuffer.depth.channels", error.frame_error.message)
        requests.send(frame_request(3))
        rendered.append(self.assert_rendered(next(responses), 3))
        for image in rendered:
            self.assertEqual(len(image.data), SIZE * SIZE * 3)

        requests.half_close()
        self.assertEqual(list(responses), [])
        self.assertEqual(responses.code(), grpc.StatusCode.OK, responses.details())

    # Step 6: float16 output (zstd-compressed when python3-zstandard is there).
    def check_float16_session(self):
        compression = (image_pb2.COMPRESSION_ZSTD if zstandard is not None
                       else image_pb2.COMPRESSION_NONE)
        requests = Requests()
        # No x-session-id: the server picks the id itself.
        responses = self.stub.Render(iter(requests), timeout=RPC_TIMEOUT_S)
        requests.send(open_request(output_dtype=image_pb2.DTYPE_FLOAT16,
                                   output_compression=compression))
        opened = next(responses)
        self.assertEqual(opened.WhichOneof("kind"), "opened", opened)
        self.assertRegex(opened.opened.session_id, r"^[0-9a-f]{32}$")
        self.assertEqual(opened.opened.settings.output_dtype, image_pb2.DTYPE_FLOAT16)
        self.assertEqual(opened.opened.settings.output_compression, compression)
        requests.send(frame_request(7))
        image = self.assert_rendered(next(responses), 7, dtype=image_pb2.DTYPE_FLOAT16,
                                     compression=compression)
        data = image.data
        if compression == image_pb2.COMPRESSION_ZSTD:
            data = zstandard.ZstdDecompressor().decompress(data)
        count = SIZE * SIZE * 3
        self.assertEqual(len(data), count * 2)
        values = struct.unpack("<%de" % count, data)
        out_of_range = [v for v in values if not 0.0 <= v <= 1.0]  # NaN fails too
        self.assertEqual(out_of_range[:5], [])
        self.assertGreater(max(values), min(values))  # an image, not a constant
        requests.half_close()
        self.assertEqual(list(responses), [])
        self.assertEqual(responses.code(), grpc.StatusCode.OK, responses.details())

    def test_list_health_reflection_render_and_sigterm(self):
        self.check_discovery()
        self.check_uint8_session()
        self.check_float16_session()
        if zstandard is None:
            sys.stderr.write("note: python3-zstandard not installed; float16 checked "
                             "without zstd\n")
        # SIGHUP rescans the model repository; without one it is refused,
        # logged, and the server keeps serving.
        self.server.proc.send_signal(signal.SIGHUP)
        self.assertTrue(self.server.wait_for_event("repository_rescan_failed"),
                        self.server.log_text())
        self.assertEqual(len(self.stub.ListEnvironments(
            render_service_pb2.ListEnvironmentsRequest(), timeout=RPC_TIMEOUT_S).environments), 1)
        # Step 7: SIGTERM with no session open: a clean, logged stop.
        self.assertEqual(self.server.terminate_and_wait(), 0, self.server.log_text())
        events = self.server.events()
        self.assertIn("server_start", events, self.server.log_text())
        self.assertIn("server_stop", events, self.server.log_text())

    def test_sigterm_drains_an_idle_session(self):
        requests = Requests()
        responses = self.stub.Render(iter(requests), metadata=(("x-session-id",
                                                                secrets.token_hex(16)),),
                                     timeout=RPC_TIMEOUT_S)
        try:
            requests.send(open_request())
            opened = next(responses)
            self.assertEqual(opened.WhichOneof("kind"), "opened", opened)
            requests.send(frame_request(1))
            self.assert_rendered(next(responses), 1)

            # The session is open and idle (its one frame answered).
            self.server.proc.send_signal(signal.SIGTERM)
            notice = next(responses)
            self.assertEqual(notice.WhichOneof("kind"), "notice", notice)
            self.assertEqual(notice.notice.reason,
                             render_service_pb2.SessionNotice.REASON_DRAINING)
            self.assertTrue(notice.notice.message)
            with self.assertRaises(grpc.RpcError) as ended:
                next(responses)
            self.assertEqual(ended.exception.code(), grpc.StatusCode.UNAVAILABLE,
                             ended.exception.details())
        finally:
            requests.half_close()  # lets grpc's request-consuming thread finish
        self.assertEqual(self.server.proc.wait(timeout=30), 0, self.server.log_text())
        self.server._drainer.join()
        events = self.server.events()
        self.assertIn("server_draining", events, self.server.log_text())
        self.assertIn("server_stop", events, self.server.log_text())

    def test_sigterm_right_after_sighup_still_drains(self):
        # SIGTERM while the main thread still handles a SIGHUP: the kernel may
        # hand it to a thread a library started before main() (OpenBLAS's
        # worker), which must forward it, not die of it. Back to back, a few
        # times on fresh servers.
        for attempt in range(3):
            server = self.server if attempt == 0 else ServerProcess()
            if attempt > 0:
                self.addCleanup(server.close)
            server.proc.send_signal(signal.SIGHUP)
            server.proc.send_signal(signal.SIGTERM)
            self.assertEqual(server.proc.wait(timeout=30), 0, server.log_text())
            server._drainer.join()
            self.assertIn("server_draining", server.events(), server.log_text())


class RepositoryReloadTest(unittest.TestCase):
    """SIGHUP with a --model_repository, through the real signal path of the
    real binary: a changed environment is reloaded (ListEnvironments shows
    the new environment.json) while a session on it keeps rendering, and a
    corrupt folder that appeared is FAILED with a reason naming its file;
    the healthy environment stays READY."""

    def setUp(self):
        self.repo = tempfile.mkdtemp(prefix="fd_interop_repository_")
        self.addCleanup(shutil.rmtree, self.repo, True)
        shutil.copytree(os.path.join(ENVIRONMENTS_DIR, "room"), os.path.join(self.repo, "room"))
        self.server = ServerProcess(("--model_repository", self.repo))
        self.addCleanup(self.server.close)
        self.stub = render_service_pb2_grpc.FrameDiffuserStub(self.server.channel)

    def loads(self, name, records=None):
        records = self.server.records() if records is None else records
        return sum(1 for r in records
                   if r.get("event") in ("environment_load", "environment_load_failed")
                   and r.get("environment") == name)

    def environments(self):
        envs = self.stub.ListEnvironments(render_service_pb2.ListEnvironmentsRequest(),
                                          timeout=RPC_TIMEOUT_S).environments
        return {env.name: env for env in envs}

    def render(self, requests, responses, index):
        requests.send(frame_request(index))
        response = next(responses)
        self.assertEqual(response.WhichOneof("kind"), "frame", response)
        self.assertEqual(response.frame.frame_index, index)

    def test_sighup_reloads_a_changed_environment_and_reports_a_corrupt_one(self):
        self.assertTrue(self.server.wait_for_log(lambda r: self.loads("room", r) >= 1),
                        self.server.log_text())
        room = self.environments()["room"]
        self.assertEqual(room.readiness, render_service_pb2.READINESS_READY, room)
        self.assertNotEqual(room.description, "reloaded by SIGHUP")

        requests = Requests()
        responses = self.stub.Render(iter(requests), timeout=RPC_TIMEOUT_S)
        try:
            requests.send(render_service_pb2.RenderRequest(open=render_service_pb2.OpenSession(
                environment="room", width=SIZE, height=SIZE, steps=2, seed=3)))
            self.assertEqual(next(responses).WhichOneof("kind"), "opened")
            self.render(requests, responses, 0)

            # room's environment.json changes; a folder with a truncated UNet
            # appears beside it.
            settings_path = os.path.join(self.repo, "room", "environment.json")
            with open(settings_path) as f:
                settings = json.load(f)
            settings["description"] = "reloaded by SIGHUP"
            with open(settings_path + ".tmp", "w") as f:
                json.dump(settings, f)
            os.replace(settings_path + ".tmp", settings_path)
            shutil.copytree(os.path.join(self.repo, "room"), os.path.join(self.repo, "broken"))
            unet = os.path.join(self.repo, "broken", "unet", "diffusion_pytorch_model.safetensors")
            with open(unet, "r+b") as f:
                f.truncate(1000)

            self.server.proc.send_signal(signal.SIGHUP)
            self.assertTrue(self.server.wait_for_log(
                lambda r: self.loads("room", r) >= 2 and self.loads("broken", r) >= 1),
                self.server.log_text())
            self.assertIn("repository_rescan", self.server.events())

            envs = self.environments()
            self.assertEqual(envs["room"].readiness, render_service_pb2.READINESS_READY,
                             envs["room"])
            self.assertEqual(envs["room"].description, "reloaded by SIGHUP")
            self.assertEqual(envs["broken"].readiness, render_service_pb2.READINESS_FAILED,
                             envs["broken"])
            self.assertIn("diffusion_pytorch_model.safetensors", envs["broken"].readiness_detail)
            self.assertLess(len(envs["broken"].readiness_detail), 1024)

            # The open session keeps rendering (on the reloaded weights).
            self.render(requests, responses, 1)
        finally:
            requests.half_close()
        self.assertEqual(list(responses), [])
        self.assertEqual(responses.code(), grpc.StatusCode.OK, responses.details())
        self.assertEqual(self.server.terminate_and_wait(), 0, self.server.log_text())


def main():
    global SERVER_BINARY
    if len(sys.argv) < 2 or not os.access(sys.argv[1], os.X_OK):
        sys.stderr.write("usage: python_interop_test.py SERVER_BINARY [unittest args]\n")
        return 2
    SERVER_BINARY = sys.argv[1]
    program = unittest.main(argv=[sys.argv[0]] + sys.argv[2:], exit=False, verbosity=2)
    return 0 if program.result.wasSuccessful() else 1


if __name__ == "__main__":
    sys.exit(main())
