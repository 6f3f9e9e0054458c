"""Every command block of README.md and docs/tutorial.md runs, in the order of the page, in
a scratch directory holding links to scenarios/ and examples/ (what a reader in a checkout
has).

The suite shortens what would take minutes and says how, here: :data:`SHORTER` (the
horizon of each scenario), :data:`REPLACE` (option values: fewer red-team evaluations,
seeds and workers, free ports) and :data:`APPEND` (no progress bar, no Rerun recording
where the step is not about it). The exceptions, with their reasons, are
:data:`NOT_RUN`: installing the package (the suite runs inside that installation), the
full CI command (``.ci/run`` runs it verbatim) and Docker (``tests/deploy/test_docker.py``
runs compose files written by ``rse compose`` where an engine exists). ``pip install`` of
the example plugin is replaced by a ``dist-info`` on ``PYTHONPATH`` declaring the same
entry point (``tests/test_example_plugins.py`` installs the package for real).
"""

from __future__ import annotations

import os
import re
import shlex
import socket
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

from tests.conftest import ROOT

PAGES = {"README": ROOT / "README.md", "tutorial": ROOT / "docs" / "tutorial.md"}

#: commands the suite does not run, and why
NOT_RUN = {
    r"^pip install -e \.( |$)|^pip install -e '\.\[test\]'": "installs this package: the suite runs inside that installation",
    r"^ruff check \.$|^mypy$|^pytest -q$": "the full CI command: .ci/run runs it verbatim",
    r"^docker( |-compose )": "needs a Docker engine: tests/deploy/test_docker.py runs rse compose's files where one exists",
}
PLUGIN_INSTALL = r"^pip install .*examples/wmsr_plugin$"

#: the horizon each scenario runs to here, by file stem (the pages run the full horizon)
SHORTER = {
    "lee_kim_shim": ["--set", "run.duration=2"],
    "lee_kim_shim_nonresilient": ["--set", "run.duration=2"],
    # my_plant.toml and the red team's worst.toml run their full 30 s (3,001 rounds of 5 agents: cheap)
    "wmsr_byzantine": ["--set", "run.rounds=30"],
}
#: option values replaced here: (option, value on the page) -> value in the suite
REPLACE = {
    ("--budget", "40"): "4",
    ("--jobs", "2"): "1",
    ("--seeds", "2"): "1",
    ("--web-port", "9090"): "FREE",  # a free port of this machine (other runs may hold 9090)
    ("--grpc-port", "9876"): "FREE",
}


def _free_port() -> str:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return str(s.getsockname()[1])
#: the exit status a command of a page is meant to have (0 for every other)
EXIT = {"rse simulate my_plant.toml --set estimator.variant=linear --out runs/mine-linear": 3}  # fails its bound
#: options added per sub-command (no progress bar, no recording where the step is not about it)
APPEND = {
    "simulate": ["--no-progress", "--no-rerun"],
    "run": ["--no-progress", "--no-rerun"],
    "redteam": ["--no-progress", "--no-rerun", "--no-png", "--shrink-budget", "2"],
    "sweep": ["--no-rrd"],
}


def bash_blocks(text: str) -> list[str]:
    """The bodies of the ```bash blocks of a markdown page, in order."""
    return re.findall(r"^```bash\n(.*?)^```$", text, flags=re.S | re.M)


def commands(block: str) -> list[str]:
    """The commands of a block: heredocs whole, ``&&`` chains split, comments dropped."""
    out: list[str] = []
    lines = block.splitlines()
    i = 0
    while i < len(lines):
        line = lines[i]
        m = re.search(r"<<'(\w+)'$", line)
        if m:
            end = lines.index(m.group(1), i + 1)
            out.append("\n".join(lines[i : end + 1]))
            i = end + 1
            continue
        while line.endswith("\\"):
            i += 1
            line = line[:-1] + lines[i]
        i += 1
        words = shlex.split(line, comments=True)
        if words:
            out += [p.strip() for p in shlex.join(words).split(" '&&' ")]
    return out


def shortened(args: list[str]) -> list[str]:
    """``rse`` arguments as the suite runs them (see the module docstring)."""
    args = [REPLACE.get((args[i - 1], a), a) if i else a for i, a in enumerate(args)]
    args = [_free_port() if a == "FREE" else a for a in args]
    for a in args:
        stem = Path(a).stem if a.endswith(".toml") else None
        if stem is not None and args[0] in ("simulate", "run", "check", "redteam", "sweep", "compose"):
            return args + SHORTER.get(stem, []) + APPEND.get(args[0], [])
    return args + APPEND.get(args[0], [])


def _env(extra_path: Path | None = None) -> dict[str, str]:
    env = dict(os.environ)
    env.pop("RSE_DEBUG", None)
    env["COLUMNS"] = "200"
    paths = [str(extra_path)] if extra_path else []
    env["PYTHONPATH"] = os.pathsep.join([*paths, str(ROOT), *filter(None, [env.get("PYTHONPATH")])])
    return env


def _rse(args: list[str], cwd: Path, env: dict[str, str]) -> subprocess.CompletedProcess:
    cmd = [sys.executable, "-m", "agents.cli", *args]
    return subprocess.run(cmd, cwd=cwd, env=env, capture_output=True, text=True, timeout=300)


def _rse_inprocess(args: list[str]) -> tuple[int, str]:
    from click.testing import CliRunner

    from agents.cli import cli

    res = CliRunner().invoke(cli, args)
    assert res.exception is None or isinstance(res.exception, SystemExit), repr(res.exception)
    return res.exit_code, res.output


def _serve_web(args: list[str], monkeypatch) -> None:
    """A served run: the viewer's URL is printed and the run completes. The command then
    serves until Ctrl-C; here that wait returns at once (``tests/agents/test_web_viewer.py``
    starts the command as a process, fetches the page and checks that Ctrl-C ends it)."""
    import agents.cli.sim as sim

    served: list[str] = []
    monkeypatch.setattr(sim, "wait_while_serving", served.append)
    code, out = _rse_inprocess(args)
    assert code == 0 and "rerun web: http" in out and served and served[0].startswith("http"), out[-3000:]


def _plugin_site(tmp: Path) -> Path:
    """A site directory whose dist-info declares the example plugin's entry points (what
    ``pip install -e examples/wmsr_plugin`` registers) beside the package's source."""
    pkg = ROOT / "examples" / "wmsr_plugin"
    meta = tomllib.loads((pkg / "pyproject.toml").read_text())["project"]
    site = tmp / "plugin-site"
    info = site / f"{meta['name'].replace('-', '_')}-{meta.get('version', '0')}.dist-info"
    info.mkdir(parents=True)
    (info / "METADATA").write_text(f"Metadata-Version: 2.1\nName: {meta['name']}\nVersion: {meta.get('version', '0')}\n")
    eps = "".join(f"[{group}]\n" + "".join(f"{k} = {v}\n" for k, v in items.items())
                  for group, items in meta["entry-points"].items())
    (info / "entry_points.txt").write_text(eps)
    (site / "rse_wmsr").symlink_to(pkg / "rse_wmsr")
    return site


def run_page(page: Path, cwd: Path, monkeypatch, outputs: dict[str, str] | None = None) -> list[str]:
    """Run every command of ``page``; returns what was not run, with the reason (and
    fills ``outputs``: command -> what it printed, for the commands run in this process)."""
    for name in ("scenarios", "examples"):
        (cwd / name).symlink_to(ROOT / name)
    monkeypatch.chdir(cwd)
    skipped: list[str] = []
    plugin_env: dict[str, str] | None = None
    for block in bash_blocks(page.read_text()):
        for cmd in commands(block):
            why = next((w for pat, w in NOT_RUN.items() if re.search(pat, cmd)), None)
            if why is not None:
                skipped.append(f"{cmd}: {why}")
                continue
            if re.search(PLUGIN_INSTALL, cmd):
                plugin_env = _env(_plugin_site(cwd))
                continue
            if "<<" in cmd:
                r = subprocess.run(["bash", "-c", cmd], cwd=cwd, capture_output=True, text=True, timeout=30)
                assert r.returncode == 0, (cmd, r.stderr)
                continue
            words = shlex.split(cmd)
            assert words[0] == "rse", f"{page.name}: a command the suite does not know how to run: {cmd}"
            args = shortened(words[1:])
            if "--serve-web" in args:
                _serve_web([a for a in args if a != "--no-rerun"], monkeypatch)
            elif any("wmsr_plugin" in a for a in args):
                assert plugin_env is not None, "the plugin's install step comes first"
                r = _rse(args, cwd, plugin_env)
                assert r.returncode == 0 and "Traceback" not in r.stderr, (cmd, r.stdout[-2000:], r.stderr[-2000:])
            else:
                code, out = _rse_inprocess(args)
                if outputs is not None:
                    outputs[cmd] = out
                assert code == EXIT.get(cmd, 0) and "Traceback" not in out, (cmd, args, out[-3000:])
    return skipped


def test_commands_are_parsed_as_a_reader_runs_them():
    block = "pip install -e . && rse run scenarios/x.toml   # a comment\nrse check a.toml \\\n  --set k=1\n" \
            "cat > f.toml <<'EOF'\n[run]\nEOF\n"
    assert commands(block) == ["pip install -e .", "rse run scenarios/x.toml", "rse check a.toml --set k=1",
                               "cat > f.toml <<'EOF'\n[run]\nEOF"]
    assert shortened(["redteam", "my_plant.toml", "--budget", "40", "--jobs", "2"])[:6] == \
        ["redteam", "my_plant.toml", "--budget", "4", "--jobs", "1"]


def test_readme_commands_run(tmp_path, monkeypatch):
    skipped = run_page(PAGES["README"], tmp_path, monkeypatch)
    # exactly the install and CI commands are left out
    assert sorted(s.split(":")[0] for s in skipped) == sorted(
        ["pip install -e .", "pip install -e '.[test]'", "ruff check .", "mypy", "pytest -q"])


@pytest.mark.slow
def test_tutorial_commands_run(tmp_path, monkeypatch):
    page = PAGES["tutorial"]
    assert len(bash_blocks(page.read_text())) >= 9
    outputs: dict[str, str] = {}
    skipped = run_page(page, tmp_path, monkeypatch, outputs)
    assert all(s.startswith("docker") for s in skipped), skipped
    # step 5: the bound holds for the median solver and fails for the linear variant (exit 3, above)
    assert "ok" in outputs["rse simulate my_plant.toml --out runs/mine"]
    # step 7: the figure draws the algorithm's metric against the scenario's own bound
    sweep = next(v for k, v in outputs.items() if k.startswith("rse sweep my_plant.toml"))
    assert "window_max_error_inf; threshold 0.5 (the scenario's [[expect]] bound)" in sweep, sweep
    assert (tmp_path / "runs" / "mine-sweep" / "sweep.png").is_file()
    assert (tmp_path / "runs" / "mine-redteam" / "worst.toml").is_file()
    assert (tmp_path / "runs" / "mine-sweep" / "sweep.parquet").is_file()
    assert (tmp_path / "my-compose.yml").is_file() and (tmp_path / "runs" / "wmsr" / "summary.json").is_file()
