"""
The commands the README and docs/ show are run here, as a reader would run them.

- every ``spacerobot-plan`` line (its ``out/`` files written to a temporary folder instead):
  exit 0, and what it says it writes is there (a PNG, a JSON whose plan is ``ok``; for
  ``spacerobot-plan envelope``, ``envelope.csv`` and a map in its ``--out`` folder, the sweep
  run in this process: ``--workers 0``);
- ``make demo`` and ``make plan`` (the README's set-up and CLI commands), with ``OUT`` in a
  temporary folder, when the virtualenv is current (``make -q venv``): a run that would
  rebuild it is no test of the command.

``make test`` is what runs this file; ``python -m spacerobot_planner.tools.gendocs`` is run by
test_docs.py (``--check``); the benchmarks by ``make bench``; ``ros2 ...`` lines need the ROS 2
command-line tools, which no wheel provides (test_docs.py checks their names and types).
"""

import json
import os
import shlex
import subprocess
from pathlib import Path

import pytest

from spacerobot_planner.tools import cli

ROOT = Path(__file__).resolve().parent.parent
PAGES = [ROOT / "README.md"] + sorted((ROOT / "docs").glob("*.md"))


def _cli_lines():
    """(page, argv) of every spacerobot-plan command in a bash block of README.md and docs/."""
    out = []
    for page in PAGES:
        text = page.read_text()
        for block in text.split("```bash")[1:]:
            body = block.split("```")[0].replace("\\\n", " ")
            for line in body.splitlines():
                words = shlex.split(line, comments=True)
                if words and Path(words[0]).name == "spacerobot-plan":
                    out.append((page.name, words[1:]))
    return out


CLI_LINES = _cli_lines()


def test_the_docs_show_cli_commands():
    assert len(CLI_LINES) >= 3, CLI_LINES


@pytest.mark.parametrize("page, argv", CLI_LINES, ids=[" ".join(a)[:60] for _, a in CLI_LINES])
def test_cli_command_shown_runs(page, argv, tmp_path, monkeypatch):
    monkeypatch.chdir(ROOT)                   # the commands are written for the repository root
    made = []
    args = []
    for a in argv:
        if a.startswith("out/"):
            a = str(tmp_path / a)
            made.append(Path(a))
        args.append(a)
    if args[:1] == ["envelope"] and not {"--workers", "--scheduler"} & set(args):
        args += ["--workers", "0"]        # in this process: test_envelope.py starts the Dask clusters
    assert cli.main(args) == 0, f"{page}: spacerobot-plan {' '.join(argv)}"
    for path in made:
        if argv[:1] == ["envelope"] and path.is_dir():      # --out DIR: the table and the maps
            assert (path / "envelope.csv").is_file(), f"{page}: no envelope.csv in {path.name}"
            assert [p.read_bytes()[:8] for p in path.glob("*.png")][:1] == [b"\x89PNG\r\n\x1a\n"], \
                f"{page}: no map in {path.name}"
            continue
        assert path.is_file() and path.stat().st_size > 0, f"{page}: {path.name} not written"
        if path.suffix == ".json":
            assert json.loads(path.read_text())["code"] == "ok"
        if path.suffix == ".png":
            assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def _venv_current() -> bool:
    r = subprocess.run(["make", "-q", "venv"], cwd=ROOT, capture_output=True)
    return r.returncode == 0


@pytest.mark.parametrize("target, figure", [("demo", "demo_paper_3dof.png"), ("plan", "paper_3dof.png")])
def test_make_target_shown_runs(target, figure, tmp_path):
    if not _venv_current():
        pytest.skip("the virtualenv is not current: `make` would rebuild it first")
    r = subprocess.run(["make", target, f"OUT={tmp_path}"], cwd=ROOT, capture_output=True, text=True,
                       timeout=600, env=dict(os.environ))
    assert r.returncode == 0, (r.stdout + r.stderr)[-3000:]
    assert (tmp_path / figure).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
