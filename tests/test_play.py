"""python -m marl_render.play: scripted keys move the agent as they say and produce frames; without a
display it says so in one line; the window's key handling (matplotlib's Agg canvas, no display)."""
import json
import math
import os
import subprocess
import sys
import warnings

import matplotlib
import numpy as np
import pytest
from matplotlib.backend_bases import KeyEvent
from PIL import Image

from marl_render import play
from marl_render.envs import egomotion
from marl_render.play import KeyboardWindow, Player, main

TURN = egomotion.TURN_RATE * egomotion.DT  # rad per step of a full turn


def wrapped(angle: float) -> float:
    return (angle + math.pi) % (2 * math.pi) - math.pi


def test_scripted_keys_move_the_agent_as_they_say(tmp_path, capsys):
    keys = "s s . . . . . . . . w w a a d".split()
    assert main(["spread", "--keys", " ".join(keys), "--others", "noop", "--frames", str(tmp_path)]) == 0
    record = json.loads(capsys.readouterr().out)
    assert record["agent"] == "agent_0" and record["keys"] == keys
    assert record["actions"] == [4, 4] + [0] * 8 + [1, 1, 2, 2, 3]
    poses = record["poses"]
    assert len(poses) == len(keys) + 1 and len(record["rewards"]) == len(keys)
    for key, before, after in zip(keys, poses[:-1], poses[1:], strict=True):
        turned = wrapped(after["yaw"] - before["yaw"])
        assert turned == pytest.approx({"a": TURN, "d": -TURN}.get(key, 0.0), abs=1e-5), key
        moved = np.subtract(after["position"], before["position"])
        heading = np.array([-math.sin(after["yaw"]), math.cos(after["yaw"])])
        if key == "w":
            assert moved @ heading > 0.01  # forward (from rest, or nearly: the backward steps have died down)
        if key == "s":
            assert moved @ heading < -0.01
    # The frames: the agent's 64 px view scaled 4x beside the 256 px overview, one per step and the first.
    files = sorted(os.listdir(tmp_path))
    assert record["frames"] == len(files) == len(keys) + 1
    frames = [np.asarray(Image.open(tmp_path / name)) for name in files]
    assert {frame.shape for frame in frames} == {(256, 256 + 4 + 256, 3)}
    view = [frame[:, :256] for frame in frames]
    assert (view[12] != view[13]).any()  # the view turned with "a"
    assert np.array_equal(view[3][::4, ::4], view[3][3::4, 3::4])  # whole-pixel scaling of the view


def test_without_a_display_it_says_so_in_one_line():
    env = {k: v for k, v in os.environ.items() if k not in ("DISPLAY", "WAYLAND_DISPLAY")}
    done = subprocess.run([sys.executable, "-m", "marl_render.play", "spread"], env=env, capture_output=True,
                          text=True, timeout=120)
    assert done.returncode == 2 and done.stdout == ""
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and "cannot open a window: this machine has no display" in lines[0]


@pytest.mark.parametrize("argv, words", [
    (["spread", "--keys", "w x"], "key 'x' takes no action in spread; keys: ['.', '0', '1', '2', '3', '4', 'a'"),
    (["spread", "--keys", "w", "--agent", "agent_9"], "agent must be an agent's index in [0, 3) or name"),
    (["spread", "--frames", "somewhere"], "--frames needs --keys"),
    (["no_such_task", "--keys", "w"], "unknown environment 'no_such_task'"),
    (["spread", "--keys", "w", "--overview", "0"], "overview must be"),
    (["spread", "--keys", "w", "--resolution", "0"], "resolution"),
    (["no_such_module:Task", "--keys", "w"], "task 'no_such_module:Task' names no importable class"),
])
def test_bad_arguments_are_one_clear_line(argv, words, capsys, monkeypatch):
    monkeypatch.setenv("DISPLAY", ":99")  # past the display check: the argument is the error
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert words in err and len(err.strip().splitlines()) == 1


def test_window_tracks_the_key_held_down_and_quits():
    with matplotlib.rc_context({"backend": "agg"}), warnings.catch_warnings():
        warnings.simplefilter("ignore")  # Agg cannot show a window: it says so
        window = KeyboardWindow("test", fps=1000.0)
        canvas = window.figure.canvas
        frame = np.zeros((8, 12, 3), dtype=np.uint8)
        window.show(frame)
        assert window.image.get_array().shape == (8, 12, 3)
        KeyEvent("key_press_event", canvas, "w")._process()
        assert window.held == "w" and not window.closed
        KeyEvent("key_release_event", canvas, "w")._process()
        assert window.held is None
        KeyEvent("key_press_event", canvas, "q")._process()
        assert window.closed
        matplotlib.pyplot.close(window.figure)


def test_a_task_of_ones_own_plays_by_module_and_class(capsys):
    # tests/ is on sys.path under pytest: test_sight.Peek is a user's task, never registered.
    assert main(["test_sight:Peek", "--keys", "d d", "--agent", "hider_0", "--others", "random"]) == 0
    record = json.loads(capsys.readouterr().out)
    assert record["task"] == "peek" and record["agent"] == "hider_0" and record["actions"] == [3, 3]
    assert wrapped(record["poses"][2]["yaw"] - record["poses"][0]["yaw"]) == pytest.approx(-2 * TURN, abs=1e-5)


def test_the_docstring_gives_cartpoles_force_keys_as_they_are():
    player = Player("cartpole", resolution=8, overview=8)
    try:
        top = player.env.num_actions - 1
        assert [player.action_for(str(key)) for key in range(top + 1)] == list(range(top + 1))
        with pytest.raises(ValueError, match=f"key '{top + 1}' takes no action in cartpole"):
            player.action_for(str(top + 1))
    finally:
        player.close()
    assert f"cartpole force level 0-{top})" in " ".join(play.__doc__.split())
