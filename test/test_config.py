"""Scenario files: the paper's scenes load; bad files name the field that is wrong."""

import os

from conftest import CONFIG_DIR
import numpy as np
import pytest
import yaml

from spacerobot_planner.config import PARAMETERS, load_params_file, load_scenario, scenario_from_params


def _write(tmp_path, params, node="spacerobot_planner"):
    p = tmp_path / "scene.yaml"
    p.write_text(yaml.safe_dump({node: {"ros__parameters": params}}))
    return p


def _paper_params():
    """Return the planner's view of the paper file as one nested section: /** and its own merged."""
    with open(os.path.join(CONFIG_DIR, "paper_3dof.yaml")) as f:
        doc = yaml.safe_load(f)
    return {**doc["/**"]["ros__parameters"], **doc["/**/spacerobot_planner"]["ros__parameters"]}


def test_shared_and_node_sections_merge(tmp_path):
    """/** first, then the node's own section on top (as --params-file does)."""
    p = tmp_path / "two.yaml"
    shared = _paper_params()
    p.write_text(yaml.safe_dump({"/**": {"ros__parameters": {**shared, "safety_margin_m": 0.05}},
                                 "/spacerobot_planner": {"ros__parameters": {"safety_margin_m": 0.07}},
                                 "mock_arm": {"ros__parameters": {"rate_hz": 20.0}}}))
    flat = load_params_file(p)
    assert flat["safety_margin_m"] == 0.07 and "rate_hz" not in flat
    arm = load_params_file(p, node="mock_arm")
    assert arm["safety_margin_m"] == 0.05 and arm["rate_hz"] == 20.0


def test_paper_scenes_load():
    s2 = load_scenario(os.path.join(CONFIG_DIR, "paper_2dof.yaml"))
    s3 = load_scenario(os.path.join(CONFIG_DIR, "paper_3dof.yaml"))
    assert s2.grid.shape == (181, 181) and s2.robot.planned_names == ("shoulder", "elbow")
    assert s3.grid.shape == (36, 37, 37) and s3.grid.periodic == (True, False, False)
    assert np.allclose(np.degrees(s3.start_rad), [-90, 135, 90])
    assert np.degrees(s2.robot.locked_rad[0]) == pytest.approx(160.7)


def test_defaults_are_the_paper_3dof_scene():
    sc = scenario_from_params({})
    assert sc.grid.shape == (36, 37, 37)
    assert sc.scene.target.grasp_point_m == pytest.approx([-3.27, -2.00])


def test_wildcard_node_section_is_accepted(tmp_path):
    sc = load_scenario(_write(tmp_path, _paper_params(), node="/**"))
    assert sc.robot.dof == 3


@pytest.mark.parametrize("mutate, message", [
    (lambda p: p["robot"].pop("link_lengths_m"), "missing required key.*robot.link_lengths_m"),
    (lambda p: p["robot"].update(link_lengths_m=[1.4, "two", 2.0]), r"robot.link_lengths_m\[1\]: expected a number"),
    (lambda p: p["robot"].update(link_lengths_m=[1.4, 0.0, 2.0]), "robot.link_lengths_m: 0.0 is below"),
    (lambda p: p["robot"].update(link_lengths_m=[1.4, 2.0]), "robot.link_lengths_m: expected 3 values"),
    (lambda p: p["grid"].update(cells=[36, 0, 36]), "grid.cells: 0 is below the minimum"),
    (lambda p: p["grid"].update(cells=[36, 36.5, 36]), r"grid.cells\[1\]: expected an integer"),
    (lambda p: p["grid"].update(cells=[36, 36]), "grid.cells: expected 3 values"),
    (lambda p: p.update(safety_margin_m="wide"), "safety_margin_m: expected a number"),
    (lambda p: p["robot"].update(periodic=[1, 0, 0]), r"robot.periodic\[0\]: expected true or false"),
    (lambda p: p["robot"].update(planned_joints=["attitude", "wrist"]), "robot.planned_joints:.*wrist"),
    (lambda p: p["obstacles"].update(polygons_m="[[[0, 0], [1, 0]]]"), r"obstacles\[0\]: a polygon needs at least 3"),
    (lambda p: p["obstacles"].update(polygons_m="[[[0, 0], [1, 0], [.nan, 1]]]"), r"obstacles\[0\]:.*NaN"),
    (lambda p: p["scenario"].update(start_deg=[0.0, 200.0, 0.0]), "scenario.start_deg: joint 'shoulder'"),
    (lambda p: p["target"].update(center_m=[1.0]), "target.center_m: expected"),
])
def test_bad_files_name_the_field(tmp_path, mutate, message):
    params = _paper_params()
    mutate(params)
    with pytest.raises(ValueError, match=message):
        load_scenario(_write(tmp_path, params))


def test_unreadable_and_malformed_files(tmp_path):
    with pytest.raises(ValueError, match="cannot read"):
        load_scenario(tmp_path / "nope.yaml")
    p = tmp_path / "bad.yaml"
    p.write_text("spacerobot_planner: [1, 2\n")
    with pytest.raises(ValueError, match="not valid YAML"):
        load_scenario(p)
    p.write_text("spacerobot_planner: {params: {}}\n")
    with pytest.raises(ValueError, match="ros__parameters"):
        load_scenario(p)


def test_every_parameter_has_a_description_and_a_valid_default():
    from spacerobot_planner.config import check_value
    for spec in PARAMETERS:
        assert spec.description
        check_value(spec.name, spec.default)


def test_arrays_from_ros_messages_are_lists():
    """`ros2 param set` / the parameter service deliver arrays as array.array: accepted."""
    import array

    from spacerobot_planner.config import check_value
    assert check_value("grid.cells", array.array("q", [36, 37, 38])) == [36, 37, 38]
    assert check_value("safety_margin_m", 0.03) == 0.03
    assert check_value("trajectory.max_velocity_deg_s", array.array("d", [1.0, 2.0, 3.0])) == [1.0, 2.0, 3.0]


def test_a_list_that_came_as_a_string_says_how_to_write_it():
    """
    ``ros2 param set NODE NAME "[0.5, 2, 2]"`` sends a string (integers and decimals mixed): the error says so.

    Before, it said only "expected a non-empty list, got '[0.5, 2, 2]'", as if no list had been given.
    """
    from spacerobot_planner.config import check_value
    with pytest.raises(ValueError) as e:
        check_value("trajectory.max_acceleration_deg_s2", "[0.5, 2, 2]")
    assert "trajectory.max_acceleration_deg_s2" in str(e.value)
    assert "write every number with a decimal point, [0.5, 2.0, 2.0]" in str(e.value), str(e.value)
    with pytest.raises(ValueError) as e:                 # an integer list: no decimals to suggest
        check_value("grid.cells", "[72, 72.5, 72]")
    assert "whole numbers only" in str(e.value) and "72.0" not in str(e.value), str(e.value)
    for text in ("abc", "[a, b]", "[]"):                 # not a list of numbers: no such hint
        with pytest.raises(ValueError) as e:
            check_value("trajectory.max_acceleration_deg_s2", text)
        assert "decimal point" not in str(e.value), str(e.value)


def test_planner_settings_come_from_the_parameters_and_name_bad_values(paper_scenario):
    from spacerobot_planner.config import scenario_from_params, settings_from_params
    from spacerobot_planner.planner import Planner
    sc = paper_scenario(2)
    params = dict(sc.params, **{"planner.max_start_penetration_m": 0.0, "grasp.max_approach_error_deg": 2.5})
    pl = Planner(scenario_from_params(params))
    assert pl.settings.max_start_penetration_m == 0.0 and pl.settings.max_approach_error_deg == 2.5
    assert Planner(scenario_from_params(params), max_start_penetration_m=0.01).settings.max_start_penetration_m == 0.01
    for key, bad in (("planner.max_start_penetration_m", -0.1), ("grasp.max_approach_error_deg", 200.0),
                     ("planner.solver", "magic")):
        with pytest.raises(ValueError, match=key.replace(".", r"\.")):
            settings_from_params({key: bad})
    with pytest.raises(ValueError, match="max_approach_error_deg"):
        Planner(sc, max_approach_error_deg=float("nan"))
    # the setters replace the settings (a new, equal-but-for-the-change object)
    before = pl.settings
    pl.max_grid_nodes = 1000
    assert pl.settings is not before and pl.settings.max_grid_nodes == 1000 and before.max_grid_nodes != 1000


def test_planner_max_threads_caps_the_planning_threads_kernels_and_changes_no_bit():
    """
    ``planner.max_threads`` reaches the plan (in the thread that plans) and the job; the plans are equal.

    The paper 3-DOF scene at 60³ (its first band above ``multigrid.PARALLEL_MIN_CELLS``: the field's
    loops on numba's threads): planned with one thread, with numba's own number, and as a planning
    process's job with one, the same path and field bit for bit; numba's count in the planning
    thread follows the setting, and goes back when it is 0 (``planner.threads_follow_load: false``: numba's
    number even where other work keeps cores busy); a negative one is refused by name.
    """
    import threading

    import numba

    from spacerobot_planner.config import settings_from_params
    from spacerobot_planner.planner import Planner
    from spacerobot_planner.worker import PlanJob, run_job
    from spacerobot_planner.termination import Termination

    with pytest.raises(ValueError, match="max_threads"):
        settings_from_params({"planner.max_threads": -1})
    params = dict(load_scenario(os.path.join(CONFIG_DIR, "paper_3dof.yaml")).params,
                  **{"grid.cells": [60, 60, 60], "planner.threads_follow_load": False})     # even on a busy machine
    out = {}

    def plan_in_a_thread():
        for most in (1, 0):
            sc = scenario_from_params(dict(params, **{"planner.max_threads": most}))
            assert sc.planner_settings.max_threads == most
            res = Planner(sc).plan(sc.start_rad, sc.goal_rad)
            out[most] = (res, numba.get_num_threads())
        sc = scenario_from_params(dict(params, **{"planner.max_threads": 1}))
        job = PlanJob.for_scenario(1, sc, sc.start_rad, sc.goal_rad)
        assert job.max_threads == 1
        planner = Planner(scenario_from_params(params))
        done = run_job(planner, job, Termination())
        out["job"] = (done.result, numba.get_num_threads(), planner.settings.max_threads)

    t = threading.Thread(target=plan_in_a_thread)
    t.start()
    t.join(600)
    assert not t.is_alive()
    one, zero, (job_res, job_threads, job_setting) = out[1], out[0], out["job"]
    assert one[1] == 1 and zero[1] == numba.config.NUMBA_NUM_THREADS and job_threads == 1 and job_setting == 1
    for res in (zero[0], job_res):
        assert res.ok and one[0].ok
        assert np.array_equal(res.path_rad, one[0].path_rad)
        assert np.array_equal(res.field.log_u, one[0].field.log_u)
