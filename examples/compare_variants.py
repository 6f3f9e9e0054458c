"""Compare two estimators on one attack with the public Python API only.

Lee, Kim and Shim's resilient distributed median solver against the linear (non-resilient)
baseline, under the paper's attack on sensor 1 (scenarios/lee_kim_shim*.toml), at a coarser
step than the paper's so that it runs in a few seconds::

    python examples/compare_variants.py [OUT_DIR]

Prints one table (worst regular agent's infinity-norm error before and under the attack,
per variant) and writes OUT_DIR/compare_variants.png (error norms against time) and the two
run directories.
"""

from __future__ import annotations

import sys
from pathlib import Path

import rse

rse.pin_blas_threads()  # before numpy is loaded: one BLAS thread, as the rse command does

import pandas as pd

HERE = Path(__file__).resolve().parent
SCENARIOS = HERE.parent / "scenarios"
VARIANTS = {
    "median (resilient)": SCENARIOS / "lee_kim_shim.toml",
    "linear (baseline)": SCENARIOS / "lee_kim_shim_nonresilient.toml",
}


def main(out: Path) -> pd.DataFrame:
    out.mkdir(parents=True, exist_ok=True)
    frames, rows = [], []
    for label, path in VARIANTS.items():
        exp = rse.load(path, set={"run.dt": 0.01})
        run = rse.simulate(exp)
        run.save(out / label.split()[0])
        m = run.metrics()
        m = m[m["regular"]].assign(variant=label)
        frames.append(m)
        before = m[(m["t"] > 9.0) & (m["t"] <= 10.0)]["error_inf"].max()
        lo, hi = exp.window
        under = m[(m["t"] >= lo) & (m["t"] <= hi)]["error_inf"].max()
        rows.append({"variant": label, "worst error, t in (9, 10]": before, f"worst error, t in [{lo:g}, {hi:g}]": under,
                     "expectations held": run.ok})
    table = pd.DataFrame(rows).set_index("variant")
    print(table.to_string(float_format=lambda v: f"{v:.4g}"))
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        print("matplotlib is not installed: no figure (pip install 'resilient-state-estimation[plot]')")
        return table
    worst = pd.concat(frames).groupby(["variant", "t"])["error_inf"].max().unstack(0)
    ax = worst.plot(logy=True, figsize=(8, 4), title="worst regular agent's infinity-norm error")
    ax.set_xlabel("t [s]")
    ax.axvline(10.0, color="grey", linestyle=":")
    plt.tight_layout()
    plt.savefig(out / "compare_variants.png", dpi=100)
    print(f"figure: {out / 'compare_variants.png'}")
    return table


if __name__ == "__main__":
    main(Path(sys.argv[1]) if len(sys.argv) > 1 else Path("runs") / "compare_variants")
