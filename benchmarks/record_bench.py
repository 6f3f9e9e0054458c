"""The cost of the delivery record (:mod:`agents.deliveries`): ``python -m benchmarks.record_bench``.

Prints, for ``scenarios/lee_kim_shim.toml`` in realtime at 100 Hz (5 agent processes):

* the agents' CPU per agent and round with and without the record (``rse run`` teams,
  alternated, ``--reps`` of each: user + system seconds of every agent process, sampled
  from 40% to 85% of the time they ran, so without the processes' start and end, over
  the plant's rounds in that time) and their ratio;
* the record's own CPU per agent-round, measured in-process: the writer alone
  (:meth:`~agents.deliveries.DeliveryWriter.stepped` on an agent's real inbox, 20,000
  calls) and the simulator stepping every agent alone with and without the record
  (thread CPU time); the writer's cost as a share of the realtime CPU per round without
  the record (the target: at most 10%);
* the bytes per agent-round of the records written.

The end-to-end figures move by more than the record costs on a shared machine;
the in-process figures are the precise ones (the fastest of the repetitions: the least
disturbed; the realtime figures are medians).
"""

from __future__ import annotations

import argparse
import json
import statistics
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

from .report import ROOT, BenchmarkError

SCENARIO = ROOT / "scenarios" / "lee_kim_shim.toml"


def _samples(run_dir: Path, done: threading.Event) -> list[tuple[float, float]]:
    """``(time, CPU seconds of every agent process)`` every 50 ms while all of them run
    (psutil, user + system)."""
    import psutil

    out: list[tuple[float, float]] = []
    procs = None
    while not done.is_set():
        if procs is None:
            try:
                pids = json.loads((run_dir / "team.json").read_text())["pids"]
                procs = [psutil.Process(pid) for who, pid in pids.items() if who.startswith("agent")]
            except (OSError, ValueError, KeyError, psutil.Error):
                time.sleep(0.01)
                continue
        try:
            out.append((time.monotonic(), sum(sum(p.cpu_times()[:2]) for p in procs)))
        except psutil.Error:
            break
        time.sleep(0.05)
    return out


def realtime_run(duration: float, rate: float, deliveries: bool) -> dict[str, Any]:
    """One realtime team: the agents' CPU per agent and round from 40% to 85% of the time
    their processes ran (no start, no end; the plant ticks at ``rate``), the rounds they
    skipped, the record's bytes per agent-round."""
    from agents.api import load_experiment, run_team
    from agents.deliveries import record_bytes
    from estimation.errors import RSEError

    ov = (f"run.duration={duration}", "expect=[]", f"output.window=[0.0, {duration}]")
    exp, _ = load_experiment(SCENARIO, ov, None)
    with tempfile.TemporaryDirectory(prefix="rse-record-bench-") as tmp:
        run_dir = Path(tmp) / "run"
        done, box = threading.Event(), {}

        def team() -> None:
            try:
                box["summary"] = run_team(exp, out=run_dir, mode="realtime", rate=rate, deliveries=deliveries).summary()
            except RSEError as exc:
                box["error"] = str(exc)
            finally:
                done.set()

        th = threading.Thread(target=team)
        th.start()
        samples = _samples(run_dir, done)
        th.join()
        summary = box.get("summary")
        if summary is None or len(samples) < 20:
            raise BenchmarkError(f"rse run failed: {box.get('error', 'too short to sample')}")
        size, agent_rounds = record_bytes(run_dir) if deliveries else (0, 0)
    agents = [p for who, p in summary["processes"].items() if who.startswith("agent")]
    t0, t1 = samples[0][0], samples[-1][0]
    a = next(x for x in samples if x[0] >= t0 + 0.4 * (t1 - t0))
    b = next(x for x in samples if x[0] >= t0 + 0.85 * (t1 - t0))
    rounds = (b[0] - a[0]) * rate  # the plant ticks at the rate
    return {"cpu_per_round_s": (b[1] - a[1]) / (rounds * len(agents)), "rounds": round(rounds),
            "skipped": sum(p.get("skipped", 0) for p in agents),
            "bytes_per_agent_round": size / agent_rounds if agent_rounds else None}


def inprocess_cost(rounds: int) -> tuple[float, float]:
    """Thread CPU seconds per agent-round of the simulator stepping each agent alone, with
    and without the record."""
    from agents.runs import load
    from agents.simulate import simulate

    exp = load(SCENARIO, set={"run.duration": rounds * 0.01, "expect": [], "output.window": [0.0, rounds * 0.01]})
    agent_rounds = exp.N * (exp.n_rounds + 1)
    out = []
    for deliveries in (False, True):
        with tempfile.TemporaryDirectory(prefix="rse-record-bench-") as tmp:
            t0 = time.thread_time()
            simulate(exp, batched=False, record=False, deliveries=Path(tmp) if deliveries else None)
            out.append((time.thread_time() - t0) / agent_rounds)
    return out[0], out[1]


def writer_cost(calls: int = 20000) -> float:
    """Thread CPU seconds of one :meth:`DeliveryWriter.stepped` call on agent 1's inbox of a
    simulated round (a measurement, both in-neighbours' messages), into a real file."""
    from agents.deliveries import DeliveryWriter
    from agents.runs import load
    from agents.simulate import make_channel, make_nodes

    exp = load(SCENARIO, set={"run.duration": 0.1, "expect": [], "output.window": [0.0, 0.1]})
    nodes = make_nodes(exp, make_channel(exp))
    node = nodes[0]
    for j in node.links:
        node.receive(j, 0, exp.x0.copy())
    inbox = node.open_round(1)
    y = exp.x0[:1].copy()
    with tempfile.TemporaryDirectory(prefix="rse-record-bench-") as tmp:
        w = DeliveryWriter(tmp, node.id, list(node.links), node.index_of)
        try:
            t0 = time.thread_time()
            for k in range(calls):
                w.stepped(k, y, inbox)
            return (time.thread_time() - t0) / calls
        finally:
            w.close()


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(prog="python -m benchmarks.record_bench", description=__doc__.splitlines()[0])
    ap.add_argument("--reps", type=int, default=3, help="repetitions of each measurement (default 3)")
    ap.add_argument("--duration", type=float, default=4.0, help="seconds of each realtime run (default 4)")
    ap.add_argument("--rate", type=float, default=100.0, help="realtime rate, Hz (default 100)")
    a = ap.parse_args(argv)
    with_, without = [], []
    for r in range(a.reps):
        for on, acc in ((False, without), (True, with_)):
            m = realtime_run(a.duration, a.rate, on)
            acc.append(m)
            print(f"realtime rep {r + 1} record {'on ' if on else 'off'}: {m['cpu_per_round_s'] * 1e6:7.1f} us CPU per "
                  f"agent-round (over {m['rounds']} rounds; {m['skipped']} agent-rounds skipped in the run)"
                  + (f", {m['bytes_per_agent_round']:.1f} bytes per agent-round" if on else ""), flush=True)
    c_on = statistics.median(m["cpu_per_round_s"] for m in with_)
    c_off = statistics.median(m["cpu_per_round_s"] for m in without)
    ip = [inprocess_cost(2000) for _ in range(a.reps)]
    for off, on in ip:
        print(f"in-process simulator: {off * 1e6:6.2f} us per agent-round without the record, {on * 1e6:6.2f} us with")
    wc = [writer_cost() for _ in range(a.reps)]
    print("in-process writer: " + ", ".join(f"{c * 1e6:.2f}" for c in wc) + " us per stepped() call")
    cost = min(wc)
    sim_off, sim_on = min(o for o, _ in ip), min(o for _, o in ip)
    size = statistics.median(m["bytes_per_agent_round"] for m in with_)
    print(f"\nrealtime {a.rate:g} Hz, median of {a.reps}: agent CPU per round {c_off * 1e6:.1f} us without the record, "
          f"{c_on * 1e6:.1f} us with ({(c_on / c_off - 1) * 100:+.1f}%)")
    print(f"in-process simulator, fastest of {a.reps}: {sim_off * 1e6:.2f} us per agent-round without the record, "
          f"{sim_on * 1e6:.2f} us with ({(sim_on - sim_off) * 1e6:+.2f} us)")
    print(f"the record's CPU per agent-round (the writer, fastest of {a.reps}): {cost * 1e6:.2f} us = "
          f"{cost / c_off * 100:.1f}% of the realtime CPU per round (target <= 10%)")
    print(f"bytes per agent-round: {size:.1f}")


if __name__ == "__main__":
    main()
