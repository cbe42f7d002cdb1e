"""Checks the Kubernetes manifests in deploy/k8s (kustomize).

Every YAML file must parse. Each overlay is rendered with `kubectl kustomize`
when kubectl is installed; otherwise with a small built-in subset of
kustomize (resources, components, configMapGenerator files, namespace, images,
inline JSON6902 patches: exactly what deploy/k8s uses). The rendered objects
must then agree with the server and with each other:

- the server Deployment requests a GPU (not in the cpu overlay), probes the
  server's grpc.health.v1 service natively (readiness:
  "framediffuser.v1.FrameDiffuser", liveness: "") on the gRPC port, its
  termination grace covers preStop + --drain_timeout, liveness cannot kill a
  draining pod, and it carries Prometheus scrape annotations for the
  --metrics_listen port;
- PodDisruptionBudgets and Services select existing pods and ports;
- the sticky router hashes x-session-id: Envoy's route (ring hash over the
  headless Service) or ingress-nginx's upstream-hash-by annotation.

Usage (ctest runs it so): python3 k8s_manifests_test.py REPO_ROOT
Exit 0: pass, 1: fail, 77: skipped (no python3-yaml).
"""
import copy
import os
import re
import shutil
import subprocess
import sys

try:
    import yaml
except ImportError:  # pragma: no cover - depends on the machine
    print("SKIP: python3-yaml is not installed (scripts/setup-deps.sh installs it)")
    sys.exit(77)

failures = []


def fail(message):
    failures.append(message)


# ------------------------------------------------------------ lite kustomize

def load_docs(path):
    with open(path) as f:
        return [d for d in yaml.safe_load_all(f) if d is not None]


def json_pointer_parent(doc, path):
    parts = [p.replace("~1", "/").replace("~0", "~") for p in path.lstrip("/").split("/")]
    node = doc
    for part in parts[:-1]:
        node = node[int(part)] if isinstance(node, list) else node[part]
    return node, parts[-1]


def apply_json6902(doc, ops):
    for op in ops:
        parent, key = json_pointer_parent(doc, op["path"])
        if isinstance(parent, list):
            key = len(parent) if key == "-" else int(key)
        if op["op"] == "remove":
            del parent[key]
        elif op["op"] in ("replace", "add"):
            if op["op"] == "add" and isinstance(parent, list):
                parent.insert(key, copy.deepcopy(op["value"]))
            else:
                parent[key] = copy.deepcopy(op["value"])
        else:
            raise ValueError("unsupported patch op %s" % op["op"])


def lite_build(directory, docs=None):
    """Renders a kustomization folder (the subset deploy/k8s uses). A
    Component adds to and patches the objects of the kustomization that
    lists it (`docs`), after that one's resources."""
    kfile = os.path.join(directory, "kustomization.yaml")
    k = load_docs(kfile)[0]
    docs = [] if docs is None else docs
    for entry in k.get("resources", []):
        path = os.path.normpath(os.path.join(directory, entry))
        docs.extend(lite_build(path) if os.path.isdir(path) else load_docs(path))
    for entry in k.get("components", []):
        lite_build(os.path.normpath(os.path.join(directory, entry)), docs)
    for gen in k.get("configMapGenerator", []):
        data = {}
        for entry in gen.get("files", []):
            with open(os.path.join(directory, entry)) as f:
                data[os.path.basename(entry)] = f.read()
        docs.append({"apiVersion": "v1", "kind": "ConfigMap",
                     "metadata": {"name": gen["name"]}, "data": data})
    for patch in k.get("patches", []):
        target = patch["target"]
        ops = yaml.safe_load(patch["patch"])
        for d in docs:
            if d["kind"] == target["kind"] and d["metadata"]["name"] == target["name"]:
                apply_json6902(d, ops)
    for image in k.get("images", []):
        for d in docs:
            for c in pod_spec(d).get("containers", []) if pod_spec(d) else []:
                if c.get("image", "").split(":")[0] == image["name"]:
                    c["image"] = "%s:%s" % (image.get("newName", image["name"]),
                                            image.get("newTag", "latest"))
    if "namespace" in k:
        for d in docs:
            if d["kind"] != "Namespace":
                d["metadata"]["namespace"] = k["namespace"]
    return docs


def kubectl_build(directory):
    out = subprocess.run(["kubectl", "kustomize", directory], capture_output=True, text=True,
                         timeout=120)
    if out.returncode != 0:
        fail("kubectl kustomize %s: %s" % (directory, out.stderr.strip()))
        return []
    return [d for d in yaml.safe_load_all(out.stdout) if d is not None]


def have_kubectl():
    if shutil.which("kubectl") is None:
        return False
    try:
        return subprocess.run(["kubectl", "kustomize", "--help"], capture_output=True,
                              timeout=60).returncode == 0
    except (OSError, subprocess.TimeoutExpired):
        return False


# -------------------------------------------------------------------- checks

def pod_spec(doc):
    if doc.get("kind") in ("Deployment", "StatefulSet", "DaemonSet"):
        return doc["spec"]["template"]["spec"]
    return None


def find(docs, kind, name=None):
    return [d for d in docs if d.get("kind") == kind and
            (name is None or d["metadata"]["name"] == name or
             re.fullmatch(re.escape(name) + r"-[a-z0-9]{10}", d["metadata"]["name"]))]


def parse_args(args):
    flags = {}
    for a in args:
        m = re.fullmatch(r"--([a-z_]+)(?:=(.*))?", a)
        if m:
            flags[m.group(1)] = m.group(2) if m.group(2) is not None else "true"
    return flags


def seconds(duration):
    m = re.fullmatch(r"(\d+)(ms|s|m)", duration)
    if not m:
        raise ValueError("duration %r" % duration)
    return int(m.group(1)) * {"ms": 0.001, "s": 1, "m": 60}[m.group(2)]


def selects(selector, labels):
    return all(labels.get(k) == v for k, v in selector.items())


def check_overlay(name, docs):
    where = "overlay %s" % name
    gpu = name.split()[0] != "cpu"
    namespaces = {d["metadata"].get("namespace") for d in docs if d["kind"] != "Namespace"}
    if len(namespaces) != 1 or None in namespaces:
        fail("%s: objects in namespaces %s (want one)" % (where, namespaces))
    servers = find(docs, "Deployment", "framediffuser-server")
    if len(servers) != 1:
        fail("%s: %d framediffuser-server Deployments" % (where, len(servers)))
        return
    dep = servers[0]
    spec = pod_spec(dep)
    pod_labels = dep["spec"]["template"]["metadata"]["labels"]
    if not selects(dep["spec"]["selector"]["matchLabels"], pod_labels):
        fail("%s: the Deployment's selector does not match its pods" % where)
    c = next((c for c in spec["containers"] if c["name"] == "server"), None)
    if c is None:
        fail("%s: no container 'server'" % where)
        return
    flags = parse_args(c.get("args", []))
    grpc_port = int(flags.get("listen", "0.0.0.0:50051").rsplit(":", 1)[1])
    metrics_port = int(flags.get("metrics_listen", ":0").rsplit(":", 1)[1])
    drain = seconds(flags.get("drain_timeout", "30s"))
    ports = {p["name"]: p["containerPort"] for p in c.get("ports", [])}
    if ports.get("grpc") != grpc_port or ports.get("metrics") != metrics_port:
        fail("%s: container ports %s do not match --listen/--metrics_listen" % (where, ports))
    if metrics_port == 0:
        fail("%s: no --metrics_listen" % where)
    # GPU request.
    res = c.get("resources", {})
    gpus = (res.get("requests", {}).get("nvidia.com/gpu"), res.get("limits", {}).get("nvidia.com/gpu"))
    if gpu and gpus != (1, 1):
        fail("%s: nvidia.com/gpu request/limit %s, want 1/1" % (where, gpus))
    if gpu and flags.get("device", "cpu").split(":")[0] != "cuda":
        fail("%s: GPU pod without --device=cuda" % where)
    if not gpu and gpus != (None, None):
        fail("%s: the cpu overlay still requests GPUs %s" % (where, gpus))
    # Native gRPC probes against our health service.
    ready = c.get("readinessProbe", {})
    live = c.get("livenessProbe", {})
    if ready.get("grpc", {}).get("port") != grpc_port or \
            ready["grpc"].get("service") != "framediffuser.v1.FrameDiffuser":
        fail("%s: readinessProbe must be grpc on %d, service framediffuser.v1.FrameDiffuser: %s" %
             (where, grpc_port, ready))
    if live.get("grpc", {}).get("port") != grpc_port or live["grpc"].get("service", "") != "":
        fail("%s: livenessProbe must be grpc on %d, service \"\": %s" % (where, grpc_port, live))
    elif live.get("failureThreshold", 3) * live.get("periodSeconds", 10) <= drain:
        fail("%s: liveness (%d x %d s) would kill a pod during its %g s drain" %
             (where, live.get("failureThreshold", 3), live.get("periodSeconds", 10), drain))
    # Termination grace covers preStop + drain.
    pre = c.get("lifecycle", {}).get("preStop", {}).get("exec", {}).get("command", [])
    pre_s = float(pre[1]) if len(pre) == 2 and pre[0] == "sleep" else 0
    grace = spec.get("terminationGracePeriodSeconds", 30)
    if grace < pre_s + drain + 5:
        fail("%s: terminationGracePeriodSeconds %s < preStop %g + drain %g + 5" %
             (where, grace, pre_s, drain))
    # Prometheus scrape annotations.
    ann = dep["spec"]["template"]["metadata"].get("annotations", {})
    if ann.get("prometheus.io/scrape") != "true" or \
            ann.get("prometheus.io/port") != str(metrics_port) or \
            ann.get("prometheus.io/path", "/metrics") != "/metrics":
        fail("%s: pod annotations %s do not point Prometheus at :%d/metrics" %
             (where, ann, metrics_port))
    if "auth_tokens_file" not in flags and \
            flags.get("max_sessions_per_client") != flags.get("max_sessions"):
        fail("%s: without tokens every client is one identity: set --max_sessions_per_client "
             "equal to --max_sessions" % where)
    image = c.get("image", "")
    if ":" not in image:
        fail("%s: server image %r has no tag (set by the overlay)" % (where, image))

    # PDBs and Services select real pods and ports.
    deployments = find(docs, "Deployment")
    pdbs = find(docs, "PodDisruptionBudget")
    if not any(selects(p["spec"]["selector"]["matchLabels"], pod_labels) for p in pdbs):
        fail("%s: no PodDisruptionBudget selects the server pods" % where)
    for p in pdbs:
        if not any(selects(p["spec"]["selector"]["matchLabels"],
                           d["spec"]["template"]["metadata"]["labels"]) for d in deployments):
            fail("%s: PDB %s selects no pods" % (where, p["metadata"]["name"]))
    for s in find(docs, "Service"):
        targets = [d for d in deployments
                   if selects(s["spec"]["selector"], d["spec"]["template"]["metadata"]["labels"])]
        if not targets:
            fail("%s: Service %s selects no pods" % (where, s["metadata"]["name"]))
            continue
        names = {p.get("name") for d in targets for cc in pod_spec(d)["containers"]
                 for p in cc.get("ports", [])}
        numbers = {p.get("containerPort") for d in targets for cc in pod_spec(d)["containers"]
                   for p in cc.get("ports", [])}
        for p in s["spec"]["ports"]:
            t = p.get("targetPort", p["port"])
            if t not in names and t not in numbers:
                fail("%s: Service %s targets port %s, which its pods lack" %
                     (where, s["metadata"]["name"], t))

    # Sticky routing on x-session-id.
    routers = 0
    for cm in find(docs, "ConfigMap", "framediffuser-envoy"):
        routers += 1
        envoy = yaml.safe_load(cm["data"]["envoy.yaml"])
        listeners = envoy["static_resources"]["listeners"]
        routes = [r for l in listeners for fc in l["filter_chains"] for f in fc["filters"]
                  for vh in f["typed_config"]["route_config"]["virtual_hosts"]
                  for r in vh["routes"]]
        if not routes or any(r["route"].get("hash_policy") != [{"header": {"header_name": "x-session-id"}}]
                             for r in routes):
            fail("%s: Envoy routes must hash the x-session-id header: %s" % (where, routes))
        if any(r["route"].get("timeout") not in ("0s", 0) for r in routes):
            fail("%s: Envoy routes must not time out long Render streams" % where)
        clusters = envoy["static_resources"]["clusters"]
        for cl in clusters:
            if cl.get("lb_policy") not in ("RING_HASH", "MAGLEV"):
                fail("%s: Envoy cluster %s lb_policy %s is not a consistent hash" %
                     (where, cl["name"], cl.get("lb_policy")))
            hc = [h.get("grpc_health_check", {}).get("service_name") for h in cl.get("health_checks", [])]
            if hc != ["framediffuser.v1.FrameDiffuser"]:
                fail("%s: Envoy must health-check framediffuser.v1.FrameDiffuser, has %s" % (where, hc))
            for ep in cl["load_assignment"]["endpoints"]:
                for lb in ep["lb_endpoints"]:
                    addr = lb["endpoint"]["address"]["socket_address"]
                    svc = find(docs, "Service", addr["address"].split(".")[0])
                    if not svc or svc[0]["spec"].get("clusterIP") != "None":
                        fail("%s: Envoy endpoint %s is not a headless Service here" %
                             (where, addr["address"]))
                    elif addr["port_value"] != grpc_port:
                        fail("%s: Envoy endpoint port %s != %d" % (where, addr["port_value"], grpc_port))
        envoy_deps = find(docs, "Deployment", "framediffuser-envoy")
        volumes = [v.get("configMap", {}).get("name") for d in envoy_deps
                   for v in pod_spec(d).get("volumes", [])]
        if cm["metadata"]["name"] not in volumes:
            fail("%s: no Envoy Deployment mounts ConfigMap %s" % (where, cm["metadata"]["name"]))
    for ing in find(docs, "Ingress"):
        routers += 1
        a = ing["metadata"].get("annotations", {})
        want = {"nginx.ingress.kubernetes.io/backend-protocol": "GRPC",
                "nginx.ingress.kubernetes.io/upstream-hash-by": "$http_x_session_id",
                "nginx.ingress.kubernetes.io/proxy-body-size": "0"}
        for key, value in want.items():
            if a.get(key) != value:
                fail("%s: Ingress annotation %s=%r, want %r" % (where, key, a.get(key), value))
        for rule in ing["spec"]["rules"]:
            for path in rule["http"]["paths"]:
                backend = path["backend"]["service"]
                if not find(docs, "Service", backend["name"]):
                    fail("%s: Ingress backend Service %s is missing" % (where, backend["name"]))
    if routers == 0:
        fail("%s: no session-sticky router (Envoy or ingress-nginx)" % where)


def main():
    root = os.path.join(sys.argv[1], "deploy", "k8s")
    files = 0
    for folder, _, names in os.walk(root):
        for n in names:
            if n.endswith((".yaml", ".yml")):
                files += 1
                try:
                    load_docs(os.path.join(folder, n))
                except yaml.YAMLError as e:
                    fail("%s: %s" % (os.path.join(folder, n), e))
    # The Kubernetes scrape config (Debian's promtool cannot check it: no
    # Kubernetes service discovery) keeps exactly the server pods, as job
    # "framediffuser" (the alert rules' job).
    prom_path = os.path.join(sys.argv[1], "deploy", "monitoring", "prometheus",
                             "prometheus-kubernetes.yml")
    prom = load_docs(prom_path)[0]
    jobs = {j["job_name"]: j for j in prom["scrape_configs"]}
    job = jobs.get("framediffuser")
    if job is None or "kubernetes_sd_configs" not in job:
        fail("%s: no kubernetes_sd job 'framediffuser'" % prom_path)
    else:
        keeps = {tuple(r["source_labels"]): r.get("regex") for r in job["relabel_configs"]
                 if r.get("action") == "keep"}
        base = load_docs(os.path.join(root, "base", "server-deployment.yaml"))[0]
        name = base["spec"]["template"]["metadata"]["labels"]["app.kubernetes.io/name"]
        if keeps.get(("__meta_kubernetes_pod_annotation_prometheus_io_scrape",)) != "true" or \
                keeps.get(("__meta_kubernetes_pod_label_app_kubernetes_io_name",)) != name:
            fail("%s: the framediffuser job must keep annotated pods labelled %s: %s" %
                 (prom_path, name, keeps))
    overlays = sorted(os.listdir(os.path.join(root, "overlays")))
    use_kubectl = have_kubectl()
    for o in overlays:
        directory = os.path.join(root, "overlays", o)
        # The built-in subset always runs, so the checks run on machines
        # without kubectl too; with kubectl, the real render is checked as
        # well and must hold the same objects.
        lite = lite_build(directory)
        check_overlay(o + " (built-in render)", lite)
        if use_kubectl:
            real = kubectl_build(directory)
            if real:
                check_overlay(o, real)
                key = lambda d: (d["kind"], re.sub(r"-[a-z0-9]{10}$", "", d["metadata"]["name"]),  # noqa: E731
                                 d["metadata"].get("namespace"))
                if sorted(map(key, lite)) != sorted(map(key, real)):
                    fail("overlay %s: the built-in render %s differs from kubectl's %s" %
                         (o, sorted(map(key, lite)), sorted(map(key, real))))
    if failures:
        for f in failures:
            print("FAIL: %s" % f)
        return 1
    print("OK: %d YAML files parse; overlays %s consistent (rendered with the built-in "
          "kustomize subset%s)" % (files, ", ".join(overlays),
                                   " and kubectl kustomize" if use_kubectl
                                   else "; kubectl is not installed, so not with kubectl"))
    return 0


if __name__ == "__main__":
    sys.exit(main())
