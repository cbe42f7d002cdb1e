"""Every PromQL expression in deploy/ (the Grafana dashboard and the alert
rules) uses only metric names and labels that framediffuser-server exports,
as declared in server/metrics.cc, and the dashboard and rules cover what
issue 9 asks for.

Usage (ctest runs it so): python3 promql_names_test.py REPO_ROOT
Exit 0: pass, 1: fail, 77: skipped (no python3-yaml; scripts/setup-deps.sh
installs it).
"""
import json
import os
import re
import sys

try:
    import yaml
except ImportError:  # pragma: no cover - depends on the machine
    print("SKIP: python3-yaml is not installed (scripts/setup-deps.sh installs it)")
    sys.exit(77)

# Labels Prometheus itself attaches to every scraped series (plus "le" of
# histogram buckets), and those the scrape configs in deploy/ add.
TARGET_LABELS = {"job", "instance", "le", "namespace", "pod"}
# Series Prometheus makes itself.
BUILTIN_METRICS = {"up"}
KEYWORDS = {"by", "without", "on", "ignoring", "group_left", "group_right", "bool", "and", "or",
            "unless", "offset", "inf", "nan"}
FUNCTIONS = {
    "abs", "absent", "absent_over_time", "avg", "avg_over_time", "bottomk", "ceil", "changes",
    "clamp", "clamp_max", "clamp_min", "count", "count_over_time", "count_values", "delta",
    "deriv", "exp", "floor", "group", "histogram_quantile", "idelta", "increase", "irate",
    "label_join", "label_replace", "last_over_time", "ln", "log2", "log10", "max",
    "max_over_time", "min", "min_over_time", "predict_linear", "quantile", "quantile_over_time",
    "rate", "resets", "round", "scalar", "sort", "sort_desc", "sqrt", "stddev", "stdvar", "sum",
    "sum_over_time", "time", "timestamp", "topk", "vector",
}

failures = []


def fail(message):
    failures.append(message)


def exported_metrics(metrics_cc):
    """name -> type, from the prometheus::Build*().Name("...") calls."""
    with open(metrics_cc) as f:
        source = f.read()
    found = re.findall(r'Build(Counter|Gauge|Histogram)\(\)\s*\.Name\("([a-z0-9_:]+)"\)', source)
    if not found:
        raise SystemExit("FAIL: no prometheus::Build*().Name(...) in %s" % metrics_cc)
    names = set(BUILTIN_METRICS)
    for kind, name in found:
        if kind == "Histogram":
            names.update({name + "_bucket", name + "_sum", name + "_count"})
        else:
            names.add(name)
    # Label keys: {{"key", value}} initialisers and env.With("key", ...).
    labels = set(re.findall(r'\{\{?"([a-z_]+)",', source))
    labels.update(re.findall(r'With\("([a-z_]+)"', source))
    return names, labels | TARGET_LABELS


def strip_strings(expr):
    return re.sub(r'"(?:[^"\\]|\\.)*"|\'(?:[^\'\\]|\\.)*\'', '""', expr)


def check_expr(where, expr, metrics, labels):
    """Checks one PromQL expression; returns the metric names it uses."""
    text = strip_strings(expr.replace("$__rate_interval", "5m").replace("$__interval", "1m"))
    used = set()
    # Label matchers: {name op "value", ...}
    for body in re.findall(r"\{([^{}]*)\}", text):
        for name in re.findall(r"([A-Za-z_][A-Za-z0-9_]*)\s*(?:=~|!~|!=|=)", body):
            if name not in labels:
                fail("%s: label '%s' is not exported: %s" % (where, name, expr))
    text = re.sub(r"\{[^{}]*\}", " ", text)
    text = re.sub(r"\[[^\]]*\]", " ", text)  # range and subquery selectors
    # Grouping label lists.
    for clause in re.findall(r"\b(?:by|without|on|ignoring|group_left|group_right)\s*\(([^()]*)\)",
                             text):
        for name in re.findall(r"[A-Za-z_][A-Za-z0-9_]*", clause):
            if name not in labels:
                fail("%s: grouping label '%s' is not exported: %s" % (where, name, expr))
    text = re.sub(r"\b(by|without|on|ignoring|group_left|group_right)\s*\([^()]*\)", " ", text)
    for match in re.finditer(r"[A-Za-z_:][A-Za-z0-9_:]*", text):
        token = match.group(0)
        following = text[match.end():].lstrip()
        if following.startswith("("):
            if token not in FUNCTIONS:
                fail("%s: unknown function '%s': %s" % (where, token, expr))
            continue
        if token.lower() in KEYWORDS or re.fullmatch(r"\d+[smhdwy]", token):
            continue
        before = text[:match.start()]
        if re.search(r"[0-9.]$", before):  # e.g. 1e3, 0.8
            continue
        if token not in metrics:
            fail("%s: metric '%s' is not exported by the server: %s" % (where, token, expr))
        used.add(token)
    return used


def main():
    root = sys.argv[1]
    metrics, labels = exported_metrics(os.path.join(root, "server", "metrics.cc"))

    # The dashboard.
    path = os.path.join(root, "deploy", "monitoring", "grafana", "dashboards", "framediffuser.json")
    with open(path) as f:
        dashboard = json.load(f)  # must parse
    dash_used = set()
    exprs = 0
    panels = list(dashboard.get("panels", []))
    for p in list(panels):
        panels.extend(p.get("panels", []))  # collapsed rows
    titles = []
    for panel in panels:
        titles.append(panel.get("title", ""))
        for target in panel.get("targets", []):
            expr = target.get("expr", "")
            if not expr:
                fail("dashboard panel '%s': a target without expr" % panel.get("title"))
                continue
            exprs += 1
            dash_used |= check_expr("dashboard '%s'" % panel.get("title"), expr, metrics, labels)
    for var in dashboard.get("templating", {}).get("list", []):
        query = var.get("definition", "")
        m = re.fullmatch(r"label_values\((.*),\s*([a-z_]+)\)", query)
        if var.get("type") == "query":
            if not m:
                fail("dashboard variable %s: unexpected query %r" % (var.get("name"), query))
                continue
            dash_used |= check_expr("variable %s" % var["name"], m.group(1), metrics, labels)
            if m.group(2) not in labels:
                fail("dashboard variable %s: label %s is not exported" % (var["name"], m.group(2)))
    ids = [p.get("id") for p in panels]
    if len(ids) != len(set(ids)):
        fail("dashboard: duplicate panel ids")
    # What issue 9 asks the dashboard to show.
    joined = "\n".join(t.get("expr", "") for p in panels for t in p.get("targets", []))
    wanted = {
        "frames/s": r'rate\(framediffuser_frames_total\{outcome="ok"',
        "latency p50 per stage": r"histogram_quantile\(0\.5, sum by \(le, stage\) \("
                                 r"rate\(framediffuser_frame_stage_seconds_bucket",
        "latency p99 per stage": r"histogram_quantile\(0\.99, sum by \(le, stage\) \("
                                 r"rate\(framediffuser_frame_stage_seconds_bucket",
        "active sessions": r"framediffuser_active_sessions",
        "batch size": r"framediffuser_step_batch_size_bucket",
        "queue depth": r"framediffuser_queue_depth",
        "errors by code": r"sum by \(outcome\) \(rate\(framediffuser_frames_total\{outcome!=\"ok\"",
        "device memory": r"framediffuser_device_memory_in_use_bytes",
    }
    for what, pattern in wanted.items():
        if not re.search(pattern, joined):
            fail("dashboard: no panel shows %s (/%s/)" % (what, pattern))

    # The alert rules.
    path = os.path.join(root, "deploy", "monitoring", "prometheus", "alerts.yml")
    with open(path) as f:
        rules = yaml.safe_load(f)
    alerts = {}
    for group in rules["groups"]:
        for rule in group["rules"]:
            name = rule.get("alert") or rule.get("record")
            alerts[name] = rule
            check_expr("alert %s" % name, rule["expr"], metrics, labels)
            if rule.get("alert") and rule.get("labels", {}).get("severity") not in (
                    "warning", "critical"):
                fail("alert %s: severity must be warning or critical" % name)
    for required, pattern in {
            "server down": r"^up\{",
            "p99 latency": r"histogram_quantile\(0\.99",
            "error ratio": r"framediffuser_frames_total.*\n?.*/",
            "queue saturation": r"framediffuser_queue_depth"}.items():
        if not any(re.search(pattern, r["expr"], re.S) for r in alerts.values()):
            fail("alerts.yml: no %s alert (/%s/)" % (required, pattern))

    if failures:
        for f in failures:
            print("FAIL: %s" % f)
        return 1
    print("OK: %d dashboard expressions (%d metrics) and %d alert rules use only the %d "
          "exported series names" % (exprs, len(dash_used), len(alerts), len(metrics)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
