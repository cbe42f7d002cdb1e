"""The container recipes without a Docker engine.

No Docker engine runs on the development machines, so the Dockerfiles are
thin wrappers around scripts, and this test runs those scripts here:

1. Dockerfile.cpu / Dockerfile.cuda are well formed for what they promise:
   Debian 12 stages, multi-stage with COPY --from of an earlier stage, a
   non-root USER in the final stage, a HEALTHCHECK, and every script and
   file they COPY or RUN exists; the BuildKit .dockerignore beside each keeps
   build trees out of the context.
2. The CPU image's build stage: scripts/build-release.sh --no-build stages
   this build's binaries into a temporary prefix, as it does into
   /opt/framediffuser in the image.
3. The image's ENTRYPOINT + CMD run from that prefix (ports moved to free
   ones), and the image's HEALTHCHECK command, run as written (port moved),
   reports healthy; a health check of an unknown service does not. SIGTERM
   (the STOPSIGNAL) stops the server with status 0.
4. deploy/compose/compose.yaml refers to files that exist, gives the server
   more than its drain time to stop, and its nginx uses the tested template.

Usage (ctest runs it so): python3 container_recipe_test.py REPO_ROOT BUILD_DIR
Exit 0: pass, 1: fail, 77: skipped (no python3-yaml).
"""
import json
import os
import re
import shutil
import signal
import subprocess
import sys
import tempfile

try:
    import yaml
except ImportError:  # pragma: no cover - depends on the machine
    print("SKIP: python3-yaml is not installed (scripts/setup-deps.sh installs it)")
    sys.exit(77)

failures = []


def fail(message):
    failures.append(message)


def parse_dockerfile(path):
    """[(instruction, arguments)] with continuation lines joined."""
    with open(path) as f:
        text = f.read()
    text = re.sub(r"\\\n", " ", text)
    out = []
    for line in text.splitlines():
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        word, _, rest = line.partition(" ")
        out.append((word.upper(), rest.strip()))
    return out


def check_dockerfile(root, name, required_scripts):
    path = os.path.join(root, "deploy", "docker", name)
    instructions = parse_dockerfile(path)
    args = {}
    stages = []
    users = {}
    healthcheck = None
    for word, rest in instructions:
        if word == "ARG" and "=" in rest:
            k, v = rest.split("=", 1)
            args[k] = v.strip('"')
        elif word == "FROM":
            m = re.fullmatch(r"(\S+)(?:\s+AS\s+(\S+))?", rest, re.I)
            image = re.sub(r"\$\{(\w+)\}", lambda mm: args.get(mm.group(1), mm.group(0)), m.group(1))
            if not re.fullmatch(r"debian:12(-slim)?", image):
                fail("%s: stage %s is based on %s, not Debian 12" % (name, m.group(2), image))
            stages.append(m.group(2))
        elif word == "COPY":
            parts = rest.split()
            sources = [p for p in parts[:-1] if not p.startswith("--")]
            frm = [p.split("=", 1)[1] for p in parts if p.startswith("--from=")]
            if frm:
                if frm[0] not in stages[:-1]:
                    fail("%s: COPY --from=%s is not an earlier stage" % (name, frm[0]))
            else:
                for s in sources:
                    if s != "." and not os.path.exists(os.path.join(root, s)):
                        fail("%s: COPY source %s does not exist" % (name, s))
        elif word == "USER":
            users[stages[-1]] = rest
        elif word == "HEALTHCHECK":
            healthcheck = rest
    if len(stages) < 2 or None in stages:
        fail("%s: want a multi-stage build with named stages, got %s" % (name, stages))
    final_user = users.get(stages[-1], "root")
    if final_user.split(":")[0] in ("root", "0"):
        fail("%s: the final stage runs as %s" % (name, final_user))
    text = "\n".join(r for _, r in instructions)
    for script in required_scripts:
        if script not in text:
            fail("%s: does not run %s" % (name, script))
        if not os.access(os.path.join(root, script), os.X_OK):
            fail("%s: %s is not an executable script" % (name, script))
    ignore = os.path.join(root, "deploy", "docker", name + ".dockerignore")
    if not os.path.exists(ignore) or "build/" not in open(ignore).read().split():
        fail("%s: %s must exclude build/" % (name, ignore))
    return instructions, healthcheck


def exec_form(rest):
    m = re.search(r"(\[.*\])\s*$", rest)
    return json.loads(m.group(1)) if m else None


def run_image_locally(root, build_dir, instructions, healthcheck):
    prefix = tempfile.mkdtemp(prefix="fd_image_")
    try:
        staged = subprocess.run([os.path.join(root, "scripts", "build-release.sh"), "--no-build",
                                 "--build-dir", build_dir, "--prefix", prefix],
                                capture_output=True, text=True, timeout=300)
        if staged.returncode != 0:
            fail("build-release.sh --no-build: %s%s" % (staged.stdout, staged.stderr))
            return
        env = dict(os.environ, PATH=os.path.join(prefix, "bin") + os.pathsep + os.environ["PATH"])
        entry = next(exec_form(r) for w, r in instructions if w == "ENTRYPOINT")
        cmd = next(exec_form(r) for w, r in instructions if w == "CMD")
        argv = [a.replace("0.0.0.0:50051", "127.0.0.1:0").replace("0.0.0.0:9464", "127.0.0.1:0")
                for a in entry + cmd]
        argv[0] = shutil.which(argv[0], path=env["PATH"])
        if argv[0] is None or not argv[0].startswith(prefix):
            fail("ENTRYPOINT %s is not among the staged binaries" % entry)
            return
        server = subprocess.Popen(argv, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                                  stderr=subprocess.PIPE, text=True, env=env)
        port = None
        lines = []
        for line in iter(server.stderr.readline, ""):
            lines.append(line)
            m = re.search(r"listening on port (\d+)", line)
            if m:
                port = int(m.group(1))
                break
        if port is None:
            fail("the image's server did not start: %s" % "".join(lines))
            server.wait()
            return
        try:
            check = exec_form(healthcheck)
            if not check or check[0] == "CMD":
                check = check[1:] if check else None
            if not check or "127.0.0.1:50051" not in check:
                fail("HEALTHCHECK must be an exec-form command on 127.0.0.1:50051: %s" % healthcheck)
                return
            check = [a.replace("127.0.0.1:50051", "127.0.0.1:%d" % port) for a in check]
            healthy = subprocess.run(check, capture_output=True, text=True, env=env, timeout=120)
            if healthy.returncode != 0:
                fail("HEALTHCHECK %s failed (%d): %s%s" % (check, healthy.returncode,
                                                           healthy.stdout, healthy.stderr))
            unknown = [a for a in check]
            if "--service" in unknown:
                unknown[unknown.index("--service") + 1] = "framediffuser.v1.FrameDiffuser/nope"
                bad = subprocess.run(unknown, capture_output=True, text=True, env=env, timeout=120)
                if bad.returncode == 0:
                    fail("the health check of an unknown service passed: %s" % bad.stdout)
        finally:
            server.send_signal(signal.SIGTERM)  # the image's STOPSIGNAL
            server.stderr.read()
            code = server.wait(timeout=120)
            if code != 0:
                fail("the server exited %d after SIGTERM" % code)
    finally:
        shutil.rmtree(prefix, ignore_errors=True)


def check_compose(root):
    path = os.path.join(root, "deploy", "compose", "compose.yaml")
    base = os.path.dirname(path)
    with open(path) as f:
        compose = yaml.safe_load(f)
    services = compose["services"]
    for name in ("framediffuser", "lb", "prometheus", "grafana"):
        if name not in services:
            fail("compose: no service %s" % name)
    for name, service in services.items():
        for volume in service.get("volumes", []):
            source = volume.split(":", 1)[0]
            if source.startswith("."):
                if not source.startswith("${") and not os.path.exists(os.path.join(base, source)) \
                        and source != "./models":
                    fail("compose: %s mounts %s, which does not exist" % (name, source))
    server = services.get("framediffuser", {})
    build = server.get("build", {})
    if not os.path.exists(os.path.join(base, build.get("context", ""), build.get("dockerfile", ""))):
        fail("compose: the server's Dockerfile %s does not exist" % build)
    drain = 30
    for a in server.get("command", []):
        m = re.fullmatch(r"--drain_timeout=(\d+)s", a)
        if m:
            drain = int(m.group(1))
    grace = re.fullmatch(r"(\d+)s", str(server.get("stop_grace_period", "10s")))
    if not grace or int(grace.group(1)) <= drain:
        fail("compose: stop_grace_period %s must exceed the %d s drain" %
             (server.get("stop_grace_period"), drain))
    lb = services.get("lb", {})
    mounts = " ".join(lb.get("volumes", []))
    if "../nginx/framediffuser-grpc.conf.template" not in mounts:
        fail("compose: lb must use deploy/nginx/framediffuser-grpc.conf.template")
    for var in ("FD_NGINX_LISTEN", "FD_BACKENDS", "FD_NGINX_ACCESS_LOG"):
        if var not in lb.get("environment", {}):
            fail("compose: lb does not set %s" % var)


def main():
    root, build_dir = sys.argv[1], sys.argv[2]
    cpu, healthcheck = check_dockerfile(root, "Dockerfile.cpu", [
        "scripts/setup-deps.sh", "scripts/build-release.sh", "scripts/setup-runtime-deps.sh"])
    check_dockerfile(root, "Dockerfile.cuda", ["scripts/setup-deps.sh"])
    if healthcheck is None:
        fail("Dockerfile.cpu: no HEALTHCHECK")
    else:
        run_image_locally(root, build_dir, cpu, healthcheck)
    check_compose(root)
    if failures:
        for f in failures:
            print("FAIL: %s" % f)
        return 1
    print("OK: Dockerfiles well formed; the CPU image's binaries staged by build-release.sh "
          "serve and pass its HEALTHCHECK; compose.yaml consistent")
    return 0


if __name__ == "__main__":
    sys.exit(main())
