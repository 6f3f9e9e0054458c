"""The benchmark suite of the runtime, run on demand (``python -m benchmarks``).

Four sections, each a module:

``simulate`` (:mod:`benchmarks.sim_bench`)
    The in-process simulator on ``scenarios/mitra_cells.toml`` at 16, 64, 256 and 1024
    agents: agent-rounds/s, fused values/s, the cost per fused value and its ratio to the
    16-agent figure, the build time of the scenario.
``memory`` (:mod:`benchmarks.sim_bench`)
    Peak RSS of a fresh simulator process at the same team sizes, and per agent.
``run`` (:mod:`benchmarks.run_bench`)
    ``rse run`` lockstep rounds/s at 2 to 32 agent processes next to the bare Zenoh
    skeleton's (:mod:`agents.net.skeleton`), and the peak RSS per agent process.
``sweep`` (:mod:`benchmarks.sweep_bench`)
    Runs/s of ``rse sweep`` on a small grid.

The figures are printed as one table and written as JSON with the machine and the git
commit (:mod:`benchmarks.report`), so two commits can be compared (``--compare``).
Run from a source checkout (this package is not installed with the runtime).
"""
