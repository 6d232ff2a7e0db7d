"""spacerobot-plan: exit codes, JSON, summary, bad input naming the field, plot."""

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

from spacerobot_planner.cli import main

ROOT = Path(__file__).resolve().parent.parent
P3 = str(ROOT / "config" / "paper_3dof.yaml")
P2 = str(ROOT / "config" / "paper_2dof.yaml")
JSON_KEYS = {"ok", "joint_names", "start_rad", "goal_rad", "path_rad", "grid_path_rad", "timings_s",
             "solver", "min_clearance_m", "error", "code"}


def wrap(a):
    return (np.asarray(a) + np.pi) % (2 * np.pi) - np.pi


def run(argv, capsys):
    rc = main(argv)
    out = capsys.readouterr()
    return rc, out.out, out.err


def test_paper_3dof_json(tmp_path, capsys):
    js = tmp_path / "plan.json"
    rc, out, err = run(["--params-file", P3, "--json", str(js)], capsys)
    assert rc == 0, err
    d = json.loads(js.read_text())
    assert JSON_KEYS <= set(d)
    assert d["ok"] is True and d["error"] is None and d["code"] == "ok"
    start = np.radians([-90.0, 135.0, 90.0])
    goal = np.radians([160.7, 32.8, 76.5])
    path = np.array(d["path_rad"])
    assert path.shape[1] == 3 and len(path) > 10
    assert np.allclose(path[0], start, atol=1e-12)
    assert np.allclose(wrap(path[-1] - goal), 0.0, atol=1e-12)
    assert np.allclose(d["start_rad"], start) and np.allclose(d["goal_rad"], goal)
    assert d["joint_names"] == ["attitude", "shoulder", "elbow"]
    assert d["min_clearance_m"] > 0.02
    for stage in ("cspace", "field", "descent", "smoothing", "verify", "total"):
        assert stage in d["timings_s"] and stage in out
    assert "clearance" in out and "length" in out


def test_start_and_goal_flags(tmp_path, capsys):
    js = tmp_path / "p.json"
    rc, out, err = run(["--params-file", P3, "--start-deg", "-80", "135", "90",
                        "--goal-deg", "150", "40", "70", "--json", str(js), "--quiet"], capsys)
    assert rc == 0, err
    d = json.loads(js.read_text())
    assert np.allclose(d["path_rad"][0], np.radians([-80, 135, 90]), atol=1e-12)
    assert np.allclose(wrap(np.array(d["path_rad"][-1]) - np.radians([150, 40, 70])), 0, atol=1e-12)


def test_goal_defaults_to_target_ik(tmp_path, capsys):
    doc = yaml.safe_load(Path(P3).read_text())
    del doc["/**"]["ros__parameters"]["scenario"]["goal_deg"]
    f = tmp_path / "no_goal.yaml"
    f.write_text(yaml.safe_dump(doc))
    js = tmp_path / "p.json"
    rc, out, err = run(["--params-file", str(f), "--json", str(js)], capsys)
    assert rc == 0, err
    assert np.allclose(np.degrees(json.loads(js.read_text())["goal_rad"]), [160.9, 32.3, 76.8], atol=0.2)


@pytest.mark.parametrize("extra, code", [
    (["--start-deg", "-90", "138", "93"], "start_in_collision"),
    (["--goal-deg", "-90", "138", "93"], "goal_in_collision"),
])
def test_no_path_exit_2(tmp_path, capsys, extra, code):
    js = tmp_path / "p.json"
    rc, out, err = run(["--params-file", P3, "--json", str(js)] + extra, capsys)
    assert rc == 2
    d = json.loads(js.read_text())
    assert d["ok"] is False and d["code"] == code and "collision" in d["error"]
    assert d["path_rad"] == [] and d["min_clearance_m"] is None
    assert code in out and "Traceback" not in err


def test_unreachable_target_exit_2(tmp_path, capsys):
    doc = yaml.safe_load(Path(P3).read_text())
    params = doc["/**"]["ros__parameters"]
    del params["scenario"]["goal_deg"]
    params["target"]["center_m"] = [9.0, 9.0]
    f = tmp_path / "far.yaml"
    f.write_text(yaml.safe_dump(doc))
    js = tmp_path / "p.json"
    rc, out, err = run(["--params-file", str(f), "--json", str(js)], capsys)
    assert rc == 2
    d = json.loads(js.read_text())
    assert d["code"] == "goal_unreachable" and "reach" in d["error"]


@pytest.mark.parametrize("argv, field", [
    (["--start-deg", "1", "2"], "--start-deg"),
    (["--goal-deg", "0", "0", "400"], "--goal-deg"),
    (["--goal-deg", "0", "0", "nan"], "--goal-deg"),
    (["--solver", "magic"], "--solver"),
    (["--cells", "1"], "grid.cells"),
    (["--cells", "10", "10"], "--cells"),
    (["--tolerance", "-1"], "planner.field_tolerance"),
    (["--start-deg", "a", "b", "c"], "--start-deg"),
    (["--bogus"], "--bogus"),
])
def test_bad_input_exit_1(capsys, argv, field):
    rc, out, err = run(["--params-file", P3] + argv, capsys)
    assert rc == 1
    assert field in err and "Traceback" not in err


def test_bad_params_file_exit_1(tmp_path, capsys):
    rc, out, err = run(["--params-file", str(tmp_path / "missing.yaml")], capsys)
    assert rc == 1 and "params file" in err
    doc = yaml.safe_load(Path(P3).read_text())
    doc["spacerobot_planner"]["ros__parameters"]["safety_margin_m"] = "wide"
    f = tmp_path / "bad.yaml"
    f.write_text(yaml.safe_dump(doc))
    rc, out, err = run(["--params-file", str(f)], capsys)
    assert rc == 1 and "safety_margin_m" in err


def test_grid_budget_exit_1(capsys):
    rc, out, err = run(["--params-file", P3, "--cells", "400"], capsys)
    assert rc == 1 and "grid.cells" in err and "max_grid_nodes" in err


def test_plot_2dof(tmp_path, capsys):
    png = tmp_path / "p2.png"
    rc, out, err = run(["--params-file", P2, "--cells", "90", "--plot", str(png), "--quiet"], capsys)
    assert rc == 0, err
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and png.stat().st_size > 20_000


def test_plot_without_path(tmp_path, capsys):
    png = tmp_path / "fail.png"
    rc, out, err = run(["--params-file", P3, "--start-deg", "-90", "138", "93", "--plot", str(png)], capsys)
    assert rc == 2 and png.stat().st_size > 20_000


def test_console_script_subprocess(tmp_path):
    """The real process: exit status 1 and a one-line message on bad input, no traceback."""
    exe = Path(sys.executable).parent / "spacerobot-plan"
    cmd = [str(exe)] if exe.exists() else [sys.executable, "-m", "spacerobot_planner.cli"]
    proc = subprocess.run(cmd + ["--params-file", P3, "--start-deg", "1", "2"],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 1
    assert "--start-deg" in proc.stderr and "Traceback" not in proc.stderr
