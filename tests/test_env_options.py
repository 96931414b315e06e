"""``--env-set`` text -> env options (diffgcl.envs.options) and the commands that take it."""

from __future__ import annotations

import argparse
import math

import numpy as np
import pytest

from diffgcl.envs.options import (
    add_env_options,
    env_from_args,
    make_env_from_options,
    parse_env_options,
)


def test_parse_vectors_numbers_pi_and_literals():
    opts = parse_env_options(["x0=0.5pi,-pi,0,0,target=0.3,-0.4", "horizon=80"])
    np.testing.assert_allclose(opts["x0"], [0.5 * math.pi, -math.pi, 0.0, 0.0])
    assert opts["target"] == [0.3, -0.4] and opts["horizon"] == 80.0
    two = parse_env_options("x0=[[0.75pi, 0.5pi, 0, 0], [1, 1, 0, 0]],torque_limit=400")
    np.testing.assert_allclose(two["x0"], [[0.75 * math.pi, 0.5 * math.pi, 0, 0], [1, 1, 0, 0]])
    assert two["torque_limit"] == 400.0
    assert parse_env_options("mjcf=arm2d.xml") == {"mjcf": "arm2d.xml"}
    assert parse_env_options(None) == {} and parse_env_options([]) == {}


@pytest.mark.parametrize(
    ("items", "message"),
    [
        (["x0"], "is not KEY=VALUE"),
        (["x0=1,2,3,4,tagret=0,0"], "no option 'tagret'"),
        (["x0=1,2,3"], "x0 must be [4] or [C, 4]"),
        (["target=1,2,3"], "target must be [2]"),
        (["torque_limit=-5"], "torque_limit must be positive"),
    ],
)
def test_bad_options_are_one_line_errors(items, message):
    parser = argparse.ArgumentParser()
    add_env_options(parser, ("arm",))
    args = parser.parse_args(sum((["--env-set", i] for i in items), []))
    with pytest.raises(SystemExit) as err:
        env_from_args(args)
    text = str(err.value)
    assert message in text and "\n" not in text and text.startswith("diffgcl: ")


def test_options_make_the_arm_task_and_override_recorded_ones():
    env = make_env_from_options("arm", {"x0": [2.0, 1.0, 0.0, 0.0], "target": [0.5, -0.5]})
    np.testing.assert_allclose(np.asarray(env.initial_states()), [[2.0, 1.0, 0.0, 0.0]])
    np.testing.assert_allclose(np.asarray(env.target), [0.5, -0.5])
    parser = argparse.ArgumentParser()
    parser.add_argument("--env-set", action="append", default=[])
    recorded = {"name": "arm", "options": {"x0": [2.0, 1.0, 0.0, 0.0], "target": [0.5, -0.5]}}
    env, options = env_from_args(parser.parse_args(["--env-set", "x0=1,1,0,0"]), recorded)
    assert options == {"x0": [1.0, 1.0, 0.0, 0.0], "target": [0.5, -0.5]}
    np.testing.assert_allclose(np.asarray(env.target), [0.5, -0.5])
    np.testing.assert_allclose(np.asarray(env.initial_states()), [[1.0, 1.0, 0.0, 0.0]])


def test_commands_accept_env_set():
    from diffgcl.cli import build_parser

    parser = build_parser()
    for command in (["train"], ["sweep"], ["gps"], ["demos", "out"], ["eval", "run"]):
        args = parser.parse_args([*command, "--env-set", "x0=1,1,0,0,target=0.2,0.1"])
        assert args.env_set == ["x0=1,1,0,0,target=0.2,0.1"], command


def test_demos_refuses_to_replace_a_folder_it_did_not_write(tmp_path):
    from diffgcl.cli import main

    mine = tmp_path / "notes"
    mine.mkdir()
    (mine / "todo.txt").write_text("keep me")
    with pytest.raises(SystemExit, match="not a demo dataset"):
        main(["demos", str(mine)])
    assert (mine / "todo.txt").read_text() == "keep me"
