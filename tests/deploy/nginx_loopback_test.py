"""Loopback integration test of the session-sticky nginx gRPC load balancer.

Three framediffuser-server backends (embedded default environment) sit behind
nginx configured from deploy/nginx/framediffuser-grpc.conf.template (the
shipped file, rendered with this run's ports). Sixteen framediffuser-client
processes (the CLI, i.e. the SDK with failover on) stream a generated 64x64
sequence through nginx, each as one session. Mid-stream:

1. nginx itself is killed (SIGKILL) and restarted on the same port: every
   stream breaks, and every SDK resumes through the new nginx. The hash on
   x-session-id must route each resume to the backend that holds the session
   (checked in the backends' JSON logs and in nginx's access log).
2. The backend holding the most live sessions is killed (SIGKILL): its
   sessions' SDKs fail over (resume fails, a new session opens on another
   backend from the last frame) while the other backends' sessions go on
   untouched.

Then every client must finish with every frame index of the sequence
rendered exactly once, and every session (server session id) must have lived
on exactly one backend.

nginx runs unprivileged (as "nobody" when the test runs as root) with a
temporary prefix, config, logs and pid file, listening on a free port.

Usage (ctest runs the first form):
  python3 nginx_loopback_test.py --server BIN --client BIN --scenegen BIN \\
      --template deploy/nginx/framediffuser-grpc.conf.template [--nginx /usr/sbin/nginx]
  ... --skip-lb-restart   # leave out step 1
  ... --bench 5           # no kills: frames/s through nginx vs direct, 5 rounds
                          # (docs/BENCHMARKS.md, "Load balancer (nginx) loopback")
"""
import argparse
import json
import os
import re
import select
import shutil
import signal
import socket
import statistics
import string
import subprocess
import sys
import tempfile
import threading
import time

WIDTH = HEIGHT = 64
STEPS = 2
NUM_BACKENDS = 3
# Bounds a hung run instead of hanging ctest; not a timing assertion.
WAIT_LIMIT_S = 900
NOBODY = 65534
NGINX = "nginx"  # set by main()


class TestFailure(Exception):
    pass


def check(condition, message):
    if not condition:
        raise TestFailure(message)


def free_port():
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def wait_for_exit(pid, timeout_s):
    """Waits for a process that is not our child (nginx daemonises) to end."""
    try:
        fd = os.pidfd_open(pid)
    except ProcessLookupError:
        return
    try:
        ready, _, _ = select.select([fd], [], [], timeout_s)
        check(ready, "nginx (pid %d) did not exit within %d s of SIGKILL" % (pid, timeout_s))
    finally:
        os.close(fd)


class Backend:
    """One framediffuser-server on an ephemeral port; its stderr (JSON log
    lines) is read until the listening line, then drained by a thread."""

    def __init__(self, binary, index):
        self.index = index
        args = [binary, "--listen", "127.0.0.1:0", "--threads", "1", "--log_format", "json",
                "--max_steps", "4", "--drain_timeout", "10s",
                # Without authentication every client is the same identity,
                # and the per-client cap (default 16) would cap the server.
                "--max_sessions_per_client", "256"]
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
            raise TestFailure("backend %d exited (code %s) before listening:\n%s" %
                              (index, code, "\n".join(self.lines)))
        self.address = "127.0.0.1:%d" % self.port
        self._drainer = threading.Thread(target=self._drain, daemon=True)
        self._drainer.start()

    def _drain(self):
        for line in iter(self.proc.stderr.readline, ""):
            self.lines.append(line.rstrip("\n"))

    def events(self, name=None):
        out = []
        for line in list(self.lines):
            if not line.startswith("{"):
                continue
            try:
                event = json.loads(line)
            except ValueError:
                continue
            if name is None or event.get("event") == name:
                out.append(event)
        return out

    def kill(self):
        self.proc.kill()
        self.proc.wait()
        self._drainer.join()

    def stop(self):
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(timeout=60)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        self._drainer.join()


class Nginx:
    """nginx from the shipped template, one process (master_process off),
    daemonised: `nginx` returns only once the listen socket is bound, so its
    exit status is the readiness signal."""

    def __init__(self, template, backends, port, directory):
        self.port = port
        self.dir = directory
        self.address = "127.0.0.1:%d" % port
        self.access_log = os.path.join(directory, "access.log")
        self.error_log = os.path.join(directory, "error.log")
        self.conf = os.path.join(directory, "nginx.conf")
        self.pid = None
        servers = " ".join("server %s max_fails=1 fail_timeout=10s;" % b.address
                           for b in backends)
        with open(template) as f:
            # safe_substitute: only our three ${FD_...} variables are ours;
            # nginx's own $variables stay untouched (envsubst with a list
            # does the same).
            body = string.Template(f.read()).safe_substitute(
                FD_NGINX_LISTEN=self.address, FD_BACKENDS=servers,
                FD_NGINX_ACCESS_LOG=self.access_log)
        with open(os.path.join(directory, "framediffuser-grpc.conf"), "w") as f:
            f.write(body)
        temp = lambda name: os.path.join(directory, name)  # noqa: E731
        with open(self.conf, "w") as f:
            f.write("\n".join([
                "worker_processes 1;",
                "master_process off;",
                "pid %s;" % temp("nginx.pid"),
                "error_log %s info;" % self.error_log,
                "events { worker_connections 1024; }",
                "http {",
                "  client_body_temp_path %s;" % temp("client_body"),
                "  proxy_temp_path %s;" % temp("proxy"),
                "  fastcgi_temp_path %s;" % temp("fastcgi"),
                "  uwsgi_temp_path %s;" % temp("uwsgi"),
                "  scgi_temp_path %s;" % temp("scgi"),
                "  include %s;" % temp("framediffuser-grpc.conf"),
                "}", ""]))
        if os.geteuid() == 0:
            os.chown(directory, NOBODY, NOBODY)
            for name in os.listdir(directory):
                os.chown(os.path.join(directory, name), NOBODY, NOBODY)

    def start(self):
        drop = {}
        if os.geteuid() == 0:
            drop = dict(user=NOBODY, group=NOBODY, extra_groups=[])
        result = subprocess.run([NGINX, "-p", self.dir, "-c", self.conf, "-e", self.error_log],
                                stdin=subprocess.DEVNULL, capture_output=True, text=True,
                                timeout=120, **drop)
        if result.returncode != 0:
            return "nginx exited %d: %s%s" % (result.returncode, result.stderr,
                                             self.read(self.error_log)[-2000:])
        with open(os.path.join(self.dir, "nginx.pid")) as f:
            self.pid = int(f.read().strip())
        return None

    def kill(self):
        if self.pid is None:
            return
        try:
            os.kill(self.pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
        wait_for_exit(self.pid, 60)
        self.pid = None

    @staticmethod
    def read(path):
        try:
            with open(path, errors="replace") as f:
                return f.read()
        except OSError:
            return ""


def start_nginx(template, backends, directory):
    """Picks a free port; retries with another one if it was taken meanwhile."""
    for _ in range(5):
        nginx = Nginx(template, backends, free_port(), directory)
        error = nginx.start()
        if error is None:
            return nginx
        if "Address already in use" not in error:
            raise TestFailure(error)
    raise TestFailure("nginx: no free port after 5 tries")


class ClientRun:
    """One framediffuser-client render (one session) and what it printed."""

    def __init__(self, binary, target, sequence, frames, out_dir, seed, on_line):
        self.frames = frames
        self.out_dir = out_dir
        self.done_frames = 0        # from progress lines
        self.progress_since_failover = 0  # progress lines after the last failover line
        self.held = False           # stopped with SIGSTOP by Clients.hold
        self.failovers = []         # (kind, new session id)
        self.session_ids = []       # every server session id, in order
        self.stdout = []
        self.stderr = []
        self._on_line = on_line
        args = [binary, "--server", target, "render", "--env", "default", "--input", sequence,
                "--output", out_dir, "--steps", str(STEPS), "--seed", str(seed),
                "--max-in-flight", "2"]
        self.proc = subprocess.Popen(args, stdin=subprocess.DEVNULL, stdout=subprocess.PIPE,
                                     stderr=subprocess.PIPE, text=True, errors="replace")
        self._threads = [threading.Thread(target=self._read, args=(s, o), daemon=True)
                         for s, o in ((self.proc.stdout, self.stdout),
                                      (self.proc.stderr, self.stderr))]
        for t in self._threads:
            t.start()

    def _read(self, stream, sink):
        for line in iter(stream.readline, ""):
            line = line.rstrip("\n")
            self._on_line(self, line, sink)
        self._on_line(self, None, sink)

    def current_session(self):
        return self.session_ids[-1] if self.session_ids else None

    def join(self):
        self.proc.wait()
        for t in self._threads:
            t.join()


class Clients:
    """Sixteen concurrent client runs; waits on what they print (a condition
    variable, no sleeping).

    hold(predicate) stops (SIGSTOP) each client as soon as a line it printed
    makes predicate(run) true, and release() continues them all. The phases
    of the test use it so that no client can run to its last frame before a
    kill, however fast the machine renders: a held client is frozen
    mid-stream, and sees the broken connection when it is continued."""

    def __init__(self, binary, target_of, sequence, frames, out_root, count):
        self.cv = threading.Condition()
        self.runs = []
        self._hold = None
        with self.cv:
            for i in range(count):
                self.runs.append(ClientRun(binary, target_of(i), sequence, frames,
                                           os.path.join(out_root, "s%02d" % i), 1000 + i,
                                           self._on_line))

    def _on_line(self, run, line, sink):
        with self.cv:
            if line is not None:
                sink.append(line)
                m = re.search(r"session ([0-9a-f]{32}) ->", line)
                if m and line.startswith("rendering "):
                    run.session_ids.append(m.group(1))
                m = re.match(r"progress: (\d+)/(\d+) frames", line)
                if m:
                    run.done_frames = int(m.group(1))
                    run.progress_since_failover += 1
                m = re.match(r"failover: .*; (resumed session|continuing in new session) "
                             r"([0-9a-f]{32})", line)
                if m:
                    run.failovers.append(("resumed" if m.group(1).startswith("resumed")
                                          else "new", m.group(2)))
                    if m.group(2) != run.current_session():
                        run.session_ids.append(m.group(2))
                    run.progress_since_failover = 0
            if self._hold is not None and not run.held and self._hold(run):
                self._stop(run)
            self.cv.notify_all()

    def _stop(self, run):
        if run.proc.poll() is None:
            run.proc.send_signal(signal.SIGSTOP)
            run.held = True

    def hold(self, predicate):
        """Stops every client for which predicate(run) holds, now or at a
        later line it prints."""
        with self.cv:
            self._hold = predicate
            for run in self.runs:
                if not run.held and predicate(run):
                    self._stop(run)

    def release(self, then_hold=None):
        """Continues every held client; then_hold becomes the next hold
        predicate (set before any client runs again)."""
        with self.cv:
            self._hold = then_hold
            for run in self.runs:
                if run.held:
                    run.held = False
                    if run.proc.poll() is None:
                        run.proc.send_signal(signal.SIGCONT)

    def wait(self, predicate, what):
        with self.cv:
            ok = self.cv.wait_for(lambda: predicate() or self._all_exited(), WAIT_LIMIT_S)
            check(ok and predicate(), "gave up waiting for: %s\n%s" % (what, self.summary()))

    def _all_exited(self):
        return all(r.proc.poll() is not None for r in self.runs)

    def wait_all(self):
        deadline = time.monotonic() + WAIT_LIMIT_S
        for run in self.runs:
            try:
                run.proc.wait(timeout=max(1, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                raise TestFailure("clients still running after %d s\n%s" %
                                  (WAIT_LIMIT_S, self.summary()))
            run.join()

    def kill_all(self):
        for run in self.runs:
            if run.proc.poll() is None:
                run.proc.kill()  # SIGKILL ends a stopped process too
            run.proc.wait()

    def summary(self):
        rows = []
        for i, r in enumerate(self.runs):
            rows.append("client %02d: rc=%s done=%d sessions=%s failovers=%s\n  stdout: %s\n"
                        "  stderr tail: %s" % (i, r.proc.poll(), r.done_frames, r.session_ids,
                                               r.failovers, " | ".join(r.stdout),
                                               " | ".join(r.stderr[-4:])))
        return "\n".join(rows)


def process_cpu_seconds(pid):
    """User + system CPU time of a process (not our child) from /proc."""
    with open("/proc/%d/stat" % pid) as f:
        fields = f.read().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def generate_sequence(scenegen, directory, frames):
    subprocess.run([scenegen, "--scene", "street", "--frames", str(frames), "--size",
                    "%dx%d" % (WIDTH, HEIGHT), "--threads", "1", "--out", directory],
                   check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, timeout=600)


def home_backends(backends):
    """session id -> index of every backend that logged its session_open."""
    home = {}
    for b in backends:
        for event in b.events("session_open"):
            home.setdefault(event["session_id"], []).append(b.index)
    return home


def check_frames(clients, frames):
    for i, run in enumerate(clients.runs):
        rc = run.proc.returncode
        stdout = "\n".join(run.stdout)
        check(rc == 0, "client %02d exited %s:\n%s\n%s" % (i, rc, stdout, "\n".join(run.stderr)))
        m = re.search(r"done: (\d+)/(\d+) frames .*, (\d+) failed, (\d+) failover", stdout)
        check(m is not None, "client %02d printed no summary:\n%s" % (i, stdout))
        written, total, failed = int(m.group(1)), int(m.group(2)), int(m.group(3))
        # The CLI writes one FinalImage_<index>.png per rendered frame it
        # received and counts them: `frames` files with exactly the indices
        # 0..frames-1 and a count of `frames` mean every index arrived once.
        check(written == frames and total == frames and failed == 0,
              "client %02d: %d/%d frames written, %d failed (want %d/%d, 0)" %
              (i, written, total, failed, frames, frames))
        files = sorted(os.listdir(os.path.join(run.out_dir, "FinalImage")))
        want = ["FinalImage_%04d.png" % k for k in range(frames)]
        check(files == want, "client %02d: output frames %s, want FinalImage_0000..%04d" %
              (i, files, frames - 1))


def run_test(args, tmp):
    frames = args.frames
    sequence = os.path.join(tmp, "sequence")
    generate_sequence(args.scenegen, sequence, frames)
    backends = [Backend(args.server, i) for i in range(NUM_BACKENDS)]
    nginx_dir = tempfile.mkdtemp(prefix="nginx_", dir=tmp)
    os.chmod(tmp, 0o755)
    nginx = start_nginx(args.template, backends, nginx_dir)
    clients = None
    try:
        clients = Clients(args.client, lambda i: nginx.address, sequence, frames,
                          os.path.join(tmp, "out"), args.sessions)
        live = lambda: [r for r in clients.runs if r.proc.poll() is None]  # noqa: E731

        # Phase 1: every session is streaming (each client is held once it
        # has 4 frames); kill nginx and bring it back.
        clients.hold(lambda r: r.done_frames >= 4)
        clients.wait(lambda: all(r.held for r in clients.runs), "every client has 4 frames")
        broken = {id(r): r.current_session() for r in live()}
        check(len(broken) == len(clients.runs),
              "a client exited before nginx was killed:\n%s" % clients.summary())
        first_access_log = ""
        if args.skip_lb_restart:
            broken = {}
            clients.release()
        else:
            first_access_log = Nginx.read(nginx.access_log)
            nginx.kill()
            error = nginx.start()
            check(error is None, "restarting nginx on the same port: %s" % error)
            # Each broken client fails over (resume, or a new session when a
            # rendered frame was lost in transit) and renders on; it is held
            # again at its first progress line after the failover.
            clients.release(then_hold=lambda r: r.failovers and r.progress_since_failover >= 1)
            clients.wait(lambda: all(r.held for r in clients.runs),
                         "every client failed over and rendered on after the nginx restart")

        # Phase 2: kill the backend that holds the most live sessions.
        if args.skip_lb_restart:
            clients.hold(lambda r: r.done_frames >= 8)
            clients.wait(lambda: all(r.held for r in clients.runs), "every client has 8 frames")
        home = home_backends(backends)
        with clients.cv:
            current = {id(r): r.current_session() for r in live()}
        count = [0] * NUM_BACKENDS
        for sid in current.values():
            check(sid in home, "session %s is on no backend's log" % sid)
            count[home[sid][0]] += 1
        victim = max(range(NUM_BACKENDS), key=lambda b: count[b])
        check(count[victim] > 0, "no live session left to fail over; use more --frames")
        on_victim = {key for key, sid in current.items() if home[sid][0] == victim}
        print("killing backend %d (%s) with %d of %d live sessions" %
              (victim, backends[victim].address, count[victim], len(current)), flush=True)
        backends[victim].kill()
        clients.release()
        clients.wait_all()

        # Every frame index exactly once, for every client.
        check_frames(clients, frames)

        # Every session lived on exactly one backend.
        home = home_backends(backends)
        for sid, where in home.items():
            check(len(where) == 1, "session %s was opened on backends %s" % (sid, where))
        for b in backends:
            for event in b.events("session_open"):
                check(event.get("routing_key_adopted") is True,
                      "backend %d did not adopt x-session-id as the id of session %s" %
                      (b.index, event["session_id"]))
            for event in b.events("session_resume"):
                check(home.get(event["session_id"]) == [b.index],
                      "session %s resumed on backend %d, opened on %s" %
                      (event["session_id"], b.index, home.get(event["session_id"])))
        # A resume only misses when its backend died: then the balancer
        # hashes it to the next backend, which does not know it, and the SDK
        # opens a new session from the last frame. Any other miss means the
        # hash sent a resume to the wrong backend.
        victim_sessions = {sid for sid, where in home.items() if where == [victim]}
        missed = 0
        for b in backends:
            for event in b.events("session_open_failed"):
                m = re.search(r"unknown session ([0-9a-f]{32})", event.get("message", ""))
                check(event.get("kind") == "resume" and m and m.group(1) in victim_sessions,
                      "backend %d: unexpected failed open: %s" % (b.index, event))
                missed += 1
        print("resumes of the killed backend's sessions that found no session: %d" % missed)

        # The nginx restart: each broken session's resume reached its home
        # backend (sticky hash), which logged session_resume.
        resumed = {(b.index, e["session_id"]) for b in backends for e in b.events("session_resume")}
        for run in clients.runs:
            if id(run) not in broken:
                continue
            sid = broken[id(run)]
            check((home[sid][0], sid) in resumed,
                  "session %s (backend %d) was not resumed there after the nginx restart" %
                  (sid, home[sid][0]))

        # nginx's own record of the second instance: every stream of a
        # session that lived on a surviving backend went to that backend.
        addresses = {b.address: b.index for b in backends}
        lines = Nginx.read(nginx.access_log)[len(first_access_log):].splitlines()
        render_lines = 0
        for line in lines:
            m = re.search(r'"POST /framediffuser.v1.FrameDiffuser/Render [^"]*" \d+ '
                          r'session=([0-9a-f]{32}) upstream=(\S+)', line)
            if not m or m.group(1) not in home or m.group(1) in victim_sessions:
                continue
            render_lines += 1
            check(addresses.get(m.group(2)) == home[m.group(1)][0],
                  "nginx sent a stream of session %s to %s, but it lives on backend %d:\n%s" %
                  (m.group(1), m.group(2), home[m.group(1)][0], line))
        check(render_lines > 0, "nginx logged no Render stream of a surviving session")

        # Failover: the victim's sessions moved (a new session from the last
        # frame on a survivor); the others failed over only once (the nginx
        # restart), i.e. losing a backend did not disturb them.
        lb_failovers = [1] if broken else []  # the nginx restart
        keyframe_opens = sum(1 for b in backends if b.index != victim
                             for e in b.events("session_open") if e.get("from_keyframe"))
        for i, run in enumerate(clients.runs):
            if id(run) in on_victim:
                check(run.failovers and run.failovers[-1][0] == "new" and
                      len(run.failovers) >= len(lb_failovers) + 1,
                      "client %02d (on the killed backend) failovers: %s" % (i, run.failovers))
                check(home[run.current_session()][0] != victim,
                      "client %02d ended on the killed backend" % i)
            else:
                check(len(run.failovers) == len(lb_failovers),
                      "client %02d (not on the killed backend) failed over %d times, want %d: %s" %
                      (i, len(run.failovers), len(lb_failovers), run.failovers))
        check(keyframe_opens >= len(on_victim),
              "%d sessions re-opened from a keyframe on surviving backends, want >= %d" %
              (keyframe_opens, len(on_victim)))
        per_backend = [sum(1 for sid in home if home[sid] == [b]) for b in range(NUM_BACKENDS)]
        print("OK: %d sessions x %d frames through nginx; sessions opened per backend %s; "
              "%d moved off the killed backend %d" %
              (len(clients.runs), frames, per_backend, len(on_victim), victim))
    except TestFailure:
        sys.stderr.write("nginx error log:\n%s\n" % Nginx.read(nginx.error_log)[-4000:])
        for b in backends:
            sys.stderr.write("backend %d log tail:\n%s\n" % (b.index, "\n".join(b.lines[-15:])))
        raise
    finally:
        if clients is not None:
            clients.kill_all()
        nginx.kill()
        for b in backends:
            b.stop()


def run_bench(args, tmp):
    """Aggregate frames/s of the same sessions through nginx and direct.

    Per round: "nginx" (the hash picks each session's backend), then
    "direct-same" (each client connects straight to the backend nginx picked
    for it in that round: the same load per backend, minus the proxy hop),
    then "direct-even" (client i on backend i % 3)."""
    frames = args.frames
    sequence = os.path.join(tmp, "sequence")
    generate_sequence(args.scenegen, sequence, frames)
    backends = [Backend(args.server, i) for i in range(NUM_BACKENDS)]
    nginx_dir = tempfile.mkdtemp(prefix="nginx_", dir=tmp)
    os.chmod(tmp, 0o755)
    nginx = start_nginx(args.template, backends, nginx_dir)
    modes = ("nginx", "direct-same", "direct-even")
    results = {mode: [] for mode in modes}
    results["nginx CPU ms/frame"] = []
    try:
        for rnd in range(args.bench):
            picked = None
            for mode in modes:
                out = os.path.join(tmp, "bench_%s_%d" % (mode, rnd))
                if mode == "nginx":
                    target = lambda i: nginx.address  # noqa: E731
                elif mode == "direct-same":
                    target = lambda i: backends[picked[i]].address  # noqa: E731
                else:
                    target = lambda i: backends[i % NUM_BACKENDS].address  # noqa: E731
                nginx_cpu = process_cpu_seconds(nginx.pid)
                start = time.monotonic()
                clients = Clients(args.client, target, sequence, frames, out, args.sessions)
                clients.wait_all()
                wall = time.monotonic() - start
                nginx_cpu = process_cpu_seconds(nginx.pid) - nginx_cpu
                check_frames(clients, frames)
                home = home_backends(backends)
                where = [home[r.session_ids[0]][0] for r in clients.runs]
                if mode == "nginx":
                    picked = where
                spread = [where.count(b) for b in range(NUM_BACKENDS)]
                fps = len(clients.runs) * frames / wall
                results[mode].append(fps)
                if mode == "nginx":
                    results["nginx CPU ms/frame"].append(
                        1000 * nginx_cpu / (len(clients.runs) * frames))
                print("round %d %-11s: %d sessions x %d frames in %6.2f s = %5.1f frames/s "
                      "(sessions per backend %s; nginx used %.2f CPU-s)" %
                      (rnd, mode, len(clients.runs), frames, wall, fps, spread, nginx_cpu),
                      flush=True)
                shutil.rmtree(out, ignore_errors=True)
        for mode in results:
            print("%-18s median %6.2f over %d rounds (%s)" %
                  (mode, statistics.median(results[mode]), len(results[mode]),
                   ", ".join("%.2f" % v for v in results[mode])))
    finally:
        nginx.kill()
        for b in backends:
            b.stop()


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--server", required=True)
    parser.add_argument("--client", required=True)
    parser.add_argument("--scenegen", required=True)
    parser.add_argument("--template", required=True)
    parser.add_argument("--nginx", default=shutil.which("nginx") or "/usr/sbin/nginx")
    parser.add_argument("--sessions", type=int, default=16)
    parser.add_argument("--frames", type=int, default=64)
    parser.add_argument("--bench", type=int, default=0,
                        help="rounds of the direct vs nginx benchmark (no kills); 0 = the test")
    parser.add_argument("--keep", action="store_true", help="keep the temporary folder")
    parser.add_argument("--skip-lb-restart", action="store_true",
                        help="leave out phase 1 (nginx killed and restarted)")
    args = parser.parse_args()
    if not os.access(args.nginx, os.X_OK):
        print("nginx: %s is not executable (scripts/setup-deps.sh installs nginx)" % args.nginx,
              file=sys.stderr)
        return 1
    global NGINX
    NGINX = args.nginx
    tmp = tempfile.mkdtemp(prefix="fd_nginx_loopback_")
    try:
        (run_bench if args.bench else run_test)(args, tmp)
        return 0
    except TestFailure as e:
        print("FAILED: %s" % e, file=sys.stderr)
        return 1
    finally:
        if args.keep:
            print("kept %s" % tmp)
        else:
            shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    sys.exit(main())
