"""Seconds from ``docker compose up`` until every container of a compose run is healthy.

A benchmark, not a test: it prints figures (the issue's bound is 30 s on the machine the
images are built on). For each repeat it writes the compose file of SCENARIO with ``rse
compose`` (host ports made ephemeral, the plant's start-up timeout raised as in
``test_docker.py``), runs ``up -d``, reads Docker's own ``health_status`` events, then
``down`` and checks that no container of the project is left. The run itself is not
waited for: only the start-up is measured. Needs the images (``python -m pytest -m slow
tests/deploy/test_docker.py`` builds them, or ``docker build`` as in docs/deployment.md).

::

    python -m tests.deploy.health_bench                          # mitra_cells.toml, 3 repeats
    python -m tests.deploy.health_bench scenarios/lee_kim_shim.toml --repeat 5
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

import yaml

from tests.conftest import SCENARIOS, rse
from tests.deploy import docker as dk


def once(scenario: Path, tmp: Path, timeout: float) -> dict[str, float]:
    """One ``up`` of ``scenario``'s compose file: seconds from ``up`` to each service's first
    ``healthy`` (the one-shot ``team`` left out), and ``up -d``'s and ``down``'s own wall time."""
    path = tmp / "compose.yml"
    res = rse("compose", str(scenario), "-o", str(path), "--run-id", "health-bench")
    if res.returncode != 0:
        raise SystemExit(res.stderr)
    spec = yaml.safe_load(path.read_text())
    for svc in spec["services"].values():
        if "ports" in svc:
            svc["ports"] = [p.split(":")[-1] for p in svc["ports"]]
    spec["services"]["plant"]["command"] += ["--startup-timeout", "300"]
    path.write_text(yaml.safe_dump(spec, sort_keys=False))
    services = [s for s in spec["services"] if s != "team"]
    with dk.ComposeRun(path) as run:
        run.watch_health()
        t_up = time.time()
        t_cmd = run.up()
        ids = {run.container(s): s for s in services}
        end = time.monotonic() + timeout
        seen: dict[str, float] = {}
        while len(seen) < len(services) and time.monotonic() < end:
            for cid, (t, _) in list(run.health.items()):
                if cid in ids:
                    seen.setdefault(ids[cid], t - t_up)
            time.sleep(0.5)
        t0 = time.monotonic()
        run.down()
        t_down = time.monotonic() - t0
        left = run.containers()
    if left:
        raise SystemExit(f"down left {len(left)} container(s) of project {run.project}")
    if len(seen) < len(services):
        raise SystemExit(f"not healthy within {timeout:g} s: {sorted(set(services) - set(seen))}")
    return {**seen, "_up_d": t_cmd, "_down": t_down}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scenario", nargs="?", type=Path, default=SCENARIOS / "mitra_cells.toml")
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--timeout", type=float, default=300.0, help="give up on a run after this many seconds")
    args = ap.parse_args(argv)
    why = dk.unavailable()
    if why:
        print(f"Docker: {why}", file=sys.stderr)
        return 2
    missing = [t for t in dk.TARGETS.values() if not dk.image_exists(t)]
    if missing:
        print(f"build the images first: missing {', '.join(missing)}", file=sys.stderr)
        return 2
    rows = []
    for _ in range(args.repeat):
        load = os.getloadavg()[0]
        with tempfile.TemporaryDirectory(prefix="rse-health-") as tmp:
            got = once(args.scenario, Path(tmp), args.timeout)
        t = {s: v for s, v in got.items() if not s.startswith("_")}
        last = max(t, key=t.get)
        rows.append({"all_healthy_s": round(t[last], 1), "last": last, "router_s": round(t["router"], 1),
                     "median_s": round(statistics.median(t.values()), 1), "up_d_s": round(got["_up_d"], 1),
                     "down_s": round(got["_down"], 1), "load_avg_1min": round(load, 1)})
        print(json.dumps(rows[-1]), flush=True)
    alls = [r["all_healthy_s"] for r in rows]
    print(f"{args.scenario.name}: {len(t)} containers healthy {min(alls):.1f} / {statistics.median(alls):.1f} / "
          f"{max(alls):.1f} s after up (min / median / max of {len(rows)}); no container left after down")
    return 0


if __name__ == "__main__":
    sys.exit(main())
