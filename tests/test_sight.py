"""Line of sight and LIDAR (envs/sight.py, ArenaScenario.sees / lidar): exact distances in known
geometry, agreement with what the cameras draw, and the "lidar" observation in every front end."""
import dataclasses
import math

import numpy as np
import pytest
import torch
from pettingzoo.test import parallel_api_test
from torchrl.envs.utils import check_env_specs

from marl_render.envs import (
    ArenaScenario,
    ArenaState,
    Prop,
    make_env,
    make_jax_env,
    make_parallel_env,
    make_torchrl_env,
    make_vec_env,
)
from marl_render.envs.planar import Obstacles
from marl_render.envs.sight import Circles, first_hit, horizontal_fov, lidar, line_of_sight

HIDER_RED = (0.95, 0.05, 0.05)
MARKER_GREEN = (0.05, 0.95, 0.05)
BOX_HALF = (0.6, 0.1)


@dataclasses.dataclass(frozen=True)
class PeekState(ArenaState):
    box: torch.Tensor  # [W, 1, 2]
    box_angle: torch.Tensor  # [W, 1] rad, counter-clockwise (a Prop's yaw and planar.Obstacles' angle)
    marker: torch.Tensor  # [W, 1, 2] a small green box at eye height


class Peek(ArenaScenario):
    """A seeker, a hider and a box between them; everything placed by set_state."""

    name = "peek"
    State = PeekState
    default_num_agents = 2
    agent_range = (2, 2)
    arena_half_extent = (2.0, 1.5)
    physics_terms = frozenset({"walls", "obstacles", "body_collisions", "drag"})
    team_colors = {"seeker": (0.5, 0.5, 0.5), "hider": HIDER_RED}

    def setup(self):
        self.setup_arena({"seeker": ["seeker_0"], "hider": ["hider_0"]}, state_dim=0, radius=0.15, max_speed=2.0)

    def initial_state(self):
        W = self.num_worlds
        return self.at_rest(torch.tensor([[0.0, -1.2], [1.5, 1.2]]).expand(W, 2, 2), torch.zeros(W, 2),
                            box=torch.zeros(W, 1, 2), box_angle=torch.zeros(W, 1),
                            marker=torch.full((W, 1, 2), 1.8))

    def spawn(self, generator):
        return self.initial_state()

    def props(self):
        return [Prop("box", "box", count=1, position="box", yaw="box_angle", height=0.4,
                     scale=(2 * BOX_HALF[0], 2 * BOX_HALF[1], 0.8), color=(0.3, 0.3, 0.6)),
                Prop("marker", "box", count=1, position="marker", height=0.4, scale=(0.08, 0.08, 0.08),
                     color=MARKER_GREEN)]

    def obstacles(self, state):
        half = torch.tensor(BOX_HALF, device=self.device).expand_as(state.box)
        return Obstacles(state.box, half, state.box_angle)

    def rules(self, before, moved, actions, alive, generator):
        return moved, torch.zeros_like(alive, dtype=torch.float32), torch.zeros_like(alive), {}


def placed(env, **fields):
    """Set fields of the env's state ({name: [values of world 0]}, the same in every world)."""
    state = env.get_state()
    for name, value in fields.items():
        state[name][:] = torch.as_tensor(value, dtype=state[name].dtype)
    state["vel"].zero_()
    env.set_state(state)
    return env.sim


def count(pixels: torch.Tensor, color) -> int:
    """Pixels [..., H, W, 3] of a saturated `color`, lit or in shade: its bright channels above 120, the
    others below 60 (no grey, wall or sky pixel passes)."""
    bright = torch.tensor([c > 0.5 for c in color])
    return int(torch.where(bright, pixels > 120, pixels < 60).all(-1).sum())


# ---------------------------------------------------------------------- the geometry itself
def test_first_hit_is_exact_for_walls_boxes_and_circles():
    origin = torch.tensor([[[0.5, 0.25]] * 5])  # [1, 5, 2]
    direction = torch.tensor([[[0.0, 1.0], [-1.0, 0.0], [0.0, -1.0], [1.0, 0.0], [0.6, 0.8]]])
    walls = first_hit(origin, direction, half_extent=(2.0, 1.0))
    # +y wall at 1 - 0.25; -x at 2 + 0.5; -y at 1 + 0.25; +x at 2 - 0.5; the diagonal leaves at y = 1 first.
    assert walls[0].tolist() == pytest.approx([0.75, 2.5, 1.25, 1.5, 0.75 / 0.8])
    # A box 0.2 x 0.4 centred 1 m along +x, turned by 90 degrees: 0.4 wide along x, so its face is 0.8 away.
    box = Obstacles(torch.tensor([[[1.5, 0.25]]]), torch.tensor([[[0.1, 0.2]]]), torch.tensor([[math.pi / 2]]))
    hits = first_hit(origin, direction, half_extent=(2.0, 1.0), boxes=box)
    assert hits[0, 3].item() == pytest.approx(0.8) and hits[0, :3].tolist() == pytest.approx(walls[0, :3].tolist())
    # A circle of radius 0.25 at 1 m along -y: hit 0.75 away; one that is not present hides nothing.
    circles = Circles(torch.tensor([[[0.5, -0.75], [0.5, 0.75]]]), torch.tensor([[0.25, 0.25]]),
                      torch.tensor([[True, False]]))
    hits = first_hit(origin, direction, half_extent=(2.0, 1.0), circles=circles)
    assert hits[0, 2].item() == pytest.approx(0.75) and hits[0, 0].item() == pytest.approx(0.75)
    # From inside a box or circle the distance is 0; skip makes a ray ignore a circle (its own body).
    inside = first_hit(torch.tensor([[[0.5, -0.75]]]), torch.tensor([[[1.0, 0.0]]]), half_extent=(2.0, 1.0),
                       circles=circles)
    skipped = first_hit(torch.tensor([[[0.5, -0.75]]]), torch.tensor([[[1.0, 0.0]]]), half_extent=(2.0, 1.0),
                        circles=circles, skip=torch.tensor([[[True, False]]]))
    assert inside.item() == 0.0 and skipped.item() == pytest.approx(1.5)


def test_line_of_sight_in_known_geometry():
    eye, yaw = torch.tensor([[[0.0, -1.0]]]), torch.zeros(1, 1)
    box = Obstacles(torch.tensor([[[0.0, 0.0]]]), torch.tensor([[[0.5, 0.1]]]), torch.zeros(1, 1))
    targets = torch.tensor([[[0.0, 1.0],    # behind the box
                             [1.0, 0.5],    # beside it, in the open
                             [0.0, -3.0],   # behind the observer
                             [0.0, 0.05],   # inside the box: the box that holds it does not hide it
                             [3.0, -0.9]]])  # 90 degrees to the side: outside a 90 degree view
    seen = line_of_sight(eye, yaw, targets, fov=math.pi / 2, reach=10.0, half_extent=(5.0, 5.0), boxes=box)
    assert seen[0, 0].tolist() == [False, True, False, True, False]
    near = line_of_sight(eye, yaw, targets, fov=math.pi / 2, reach=1.5, half_extent=(5.0, 5.0), boxes=box)
    assert near[0, 0].tolist() == [False, False, False, True, False]  # (1, 0.5) is 1.8 m away
    assert horizontal_fov(math.pi / 2) == pytest.approx(math.pi / 2)
    assert horizontal_fov(math.pi / 2, aspect=2.0) == pytest.approx(2 * math.atan(2.0))


# ---------------------------------------------------------------------- through the env
@pytest.fixture
def peek():
    env = make_env(Peek, num_worlds=1, resolution=64, seed=0)
    env.reset()
    yield env
    env.close()


@pytest.mark.parametrize("angle, hidden", [(0.0, True), (math.pi / 2, False)])
def test_sees_agrees_with_the_rendered_view(peek, angle, hidden):
    # The box 1.2 x 0.2 m between the seeker at (0, -1.2) and the hider at (0.7, 1.2): across the line
    # of sight it hides the hider; turned by 90 degrees (a Prop's yaw and the obstacle's angle alike)
    # it is 0.2 m wide and the hider is in the open.
    sim = placed(peek, pos=[[0.0, -1.2], [0.7, 1.2]], yaw=[0.0, math.pi], box_angle=[angle])
    seen = peek.scenario.sees(sim, "agents")
    assert seen[0].tolist() == [[False, not hidden], [not hidden, False]]
    pixels = peek.step(torch.zeros(1, 2, dtype=torch.long))[0]["pixels"]
    assert (count(pixels[0, 0], HIDER_RED) == 0) == hidden
    assert peek.scenario.sees(peek.sim, "agents")[0, 0, 1].item() == (not hidden)


@pytest.mark.parametrize("bearing, inside", [(42.0, True), (47.0, False)])
def test_horizontal_field_of_view_is_what_the_camera_shows(peek, bearing, inside):
    fov = peek.scenario.horizontal_fov()
    assert math.degrees(fov) == pytest.approx(2 * math.degrees(math.atan(math.cos(0.2))))  # 88.9 degrees
    # An 8 cm marker at eye height 1.5 m away, `bearing` degrees to the seeker's left: all of it within
    # 2.2 degrees of that bearing, so at 42 degrees it is all inside the view, at 47 all outside.
    b = math.radians(bearing)
    sim = placed(peek, pos=[[0.0, -1.2], [1.5, 1.2]], yaw=[0.0, 0.0], box=[[0.0, 1.4]],
                 marker=[[-1.5 * math.sin(b), -1.2 + 1.5 * math.cos(b)]])
    assert peek.scenario.sees(sim, "marker")[0, 0, 0].item() == inside
    view = peek.step(torch.zeros(1, 2, dtype=torch.long))[0]["pixels"][0, 0]
    assert (count(view, MARKER_GREEN) > 0) == inside


def test_sees_takes_points_props_by_name_and_refuses_other_targets(peek):
    sim = placed(peek, pos=[[0.0, -1.2], [0.7, 1.2]], yaw=[0.0, 0.0], marker=[[0.0, 1.0]])
    points = torch.tensor([[[0.0, 1.0], [0.5, -0.5]]])
    assert peek.scenario.sees(sim, points)[0, 0].tolist() == [False, True]  # behind the box; in the open
    assert peek.scenario.sees(sim, points, reach=1.0)[0, 0].tolist() == [False, True]
    assert peek.scenario.sees(sim, points, fov=0.1)[0, 0].tolist() == [False, False]
    assert peek.scenario.sees(sim, "marker")[0, 0].tolist() == [False]
    with pytest.raises(ValueError, match=r"Prop of peek \(\['box', 'marker'\]\), got 'lamp'"):
        peek.scenario.sees(sim, "lamp")
    with pytest.raises(ValueError, match=r"targets must be float points \[1, T, 2\]"):
        peek.scenario.sees(sim, torch.zeros(1, 2))
    with pytest.raises(ValueError, match="fov must be a finite number in \\(0, 2 pi\\]"):
        peek.scenario.sees(sim, "agents", fov=7.0)
    with pytest.raises(ValueError, match="fov must be a finite number > 0, got nan"):
        peek.scenario.sees(sim, "agents", fov=float("nan"))
    with pytest.raises(ValueError, match="reach must be a finite number > 0, got -1.0"):
        peek.scenario.sees(sim, "agents", reach=-1.0)


def test_lidar_distances_are_exact():
    env = make_env(Peek, num_worlds=2, resolution=8, lidar=4, seed=0)
    env.reset()
    # The seeker at (0.5, 0.25) facing +y in the 4 x 3 m arena; the hider 1 m to its -y side (a body of
    # radius 0.15 m), the box far off: ray 0 (+y) meets the wall 1.25 away, ray 1 (to the left, -x)
    # 2.5, ray 2 (-y) the hider's body 0.85, ray 3 (+x) the wall 1.5. The reach is the diagonal, 5 m.
    sim = placed(env, pos=[[0.5, 0.25], [0.5, -0.75]], yaw=[0.0, 0.0], box=[[-1.5, -1.0]])
    scan = env.scenario.lidar(sim, 4, None)
    assert scan.dtype == torch.float32 and scan.shape == (2, 2, 4)
    assert scan[0, 0].tolist() == pytest.approx([1.25 / 5, 2.5 / 5, 0.85 / 5, 1.5 / 5], abs=1e-6)
    obs = env.step(torch.zeros(2, 2, dtype=torch.long))[0]
    expected = torch.tensor([1.25 / 5, 2.5 / 5, 0.85 / 5, 1.5 / 5]).expand(2, 4)
    torch.testing.assert_close(obs["lidar"][:, 0], expected, rtol=0, atol=1e-6)
    # The hider (yaw 0 too) sees the seeker 0.85 ahead; a 1 m reach caps the far rays at 1.
    assert env.scenario.lidar(sim, 4, 1.0)[0, 1].tolist() == pytest.approx([0.85, 1.0, 0.75, 1.0], abs=1e-6)
    # The box, turned by 90 degrees, 0.3 m to the seeker's left: its face 0.2 m away along ray 1.
    sim = placed(env, box=[[0.2, 0.25]], box_angle=[math.pi / 2])
    assert env.scenario.lidar(sim, 4, None)[0, 0, 1].item() == pytest.approx(0.2 / 5, abs=1e-6)
    env.close()


def test_lidar_is_an_observation_of_every_front_end():
    pz = make_parallel_env("spread", resolution=8, lidar=6)
    space = pz.observation_space("agent_0")["lidar"]
    assert space.shape == (6,) and space.dtype == np.float32 and space.low.min() == 0 and space.high.max() == 1
    parallel_api_test(pz, num_cycles=10)
    obs, _ = pz.reset(seed=0)
    assert space.contains(obs["agent_0"]["lidar"])
    pz.close()

    trl = make_torchrl_env("spread", num_worlds=2, resolution=8, lidar=6)
    check_env_specs(trl)
    spec = trl.observation_spec["agents", "lidar"]
    assert spec.shape == (2, 3, 6) and spec.dtype == torch.float32
    assert float(spec.space.low.min()) == 0.0 and float(spec.space.high.max()) == 1.0
    td = trl.rollout(3)
    assert td["next", "agents", "lidar"].shape == (2, 3, 3, 6)
    trl.close()

    vec = make_vec_env("spread", num_worlds=2, resolution=8, lidar=6)
    obs, _ = vec.reset(seed=0)
    assert vec.single_observation_space["lidar"].shape == (6,) and obs["lidar"].shape == (6, 6)
    assert vec.observation_space.contains(obs)
    vec.close()

    jax_env = make_jax_env("spread", num_worlds=2, resolution=8, lidar=6)
    assert tuple(jax_env.reset(seed=0)["lidar"].shape) == (2, 3, 6)
    jax_env.close()


@pytest.mark.parametrize("kwargs, error, words", [
    ({"lidar": -1}, ValueError, r"lidar must be an int in \[0, 1024\] \(rays; 0: no lidar\), got -1"),
    ({"lidar": 2.0}, TypeError, r"lidar must be an int in \[0, 1024\].*got 2.0"),
    ({"lidar": True}, TypeError, r"lidar must be an int.*got True"),
    ({"lidar": 5000}, ValueError, r"lidar must be an int in \[0, 1024\].*got 5000"),
    ({"lidar": 4, "lidar_range": 0}, ValueError, r"lidar_range must be a finite number > 0, got 0"),
    ({"lidar": 4, "lidar_range": float("nan")}, ValueError, r"lidar_range must be a finite number > 0"),
    ({"lidar_range": 2.0}, ValueError, r"lidar_range applies with lidar > 0"),
])
def test_lidar_options_are_checked(kwargs, error, words):
    with pytest.raises(error, match=words):
        make_env("spread", resolution=8, **kwargs)


def test_lidar_is_refused_by_a_task_without_planar_geometry():
    with pytest.raises(ValueError, match="lidar applies to arena tasks .* cartpole has none, got lidar=8"):
        make_env("cartpole", resolution=8, lidar=8)


class Pillared(Peek):
    """Peek with a pillar: a body of infinite mass (what docs/authoring.md says round obstacles are)."""

    name = "pillared"

    def setup(self):
        self.setup_arena({"seeker": ["seeker_0"], "hider": ["hider_0"]}, state_dim=0, radius=0.15, max_speed=2.0,
                         bodies=((0.3, math.inf),))

    def initial_state(self):
        state = super().initial_state()
        W = self.num_worlds
        pos = torch.cat((state.pos, torch.tensor([0.0, 0.0]).expand(W, 1, 2)), 1)
        return self.at_rest(pos, state.yaw, box=state.box, box_angle=state.box_angle, marker=state.marker)


def test_a_pillar_is_an_immovable_body_that_hides_and_stops():
    env = make_env(Pillared, num_worlds=1, resolution=8, seed=0, lidar=4)
    env.reset()
    # The seeker at (0, -1.2) faces the pillar (radius 0.3 at the origin); the hider stands behind it.
    sim = placed(env, pos=[[0.0, -1.2], [0.0, 1.0], [0.0, 0.0]], yaw=[0.0, 0.0], box=[[1.5, 1.3]])
    assert env.scenario.sees(sim, "agents")[0, 0, 1].item() is False
    assert env.scenario.sees(sim, torch.tensor([[[0.6, 1.0]]]))[0, 0, 0].item() is True
    assert env.scenario.lidar(sim, 4, None)[0, 0, 0].item() == pytest.approx(0.9 / 5, abs=1e-6)
    for _ in range(20):  # the seeker drives into it: it stops there, the pillar does not move
        obs = env.step(torch.tensor([[1, 0]]))[0]
    assert env.sim.pos[0, 2].tolist() == [0.0, 0.0] and env.sim.vel[0, 2].tolist() == [0.0, 0.0]
    assert -0.5 < env.sim.pos[0, 0, 1].item() < -0.44  # touching: centres 0.45 apart
    assert obs["lidar"][0, 0, 0].item() == pytest.approx(0.15 / 5, abs=0.002)  # from its centre: its own radius
    env.close()


# ---------------------------------------------------------------------- the helpers' edges
ARENA = (2.0, 1.0)


def test_lidar_from_a_non_finite_eye_or_yaw_is_refused():
    for eye, yaw in ((torch.tensor([[[math.nan, 0.0]]]), torch.zeros(1, 1)),
                     (torch.tensor([[[0.0, math.inf]]]), torch.zeros(1, 1)),
                     (torch.zeros(1, 1, 2), torch.tensor([[math.nan]]))):
        with pytest.raises(ValueError, match=r"eye and yaw must be finite"):
            lidar(eye, yaw, rays=4, reach=5.0, half_extent=ARENA)


def test_an_eye_outside_the_arena_reads_zero_and_sees_nothing_beyond_itself():
    eye, yaw = torch.tensor([[[2.5, 0.0], [0.0, -1.2]]]), torch.tensor([[math.pi / 2, 0.0]])  # facing the arena
    assert lidar(eye, yaw, rays=4, reach=5.0, half_extent=ARENA).tolist() == [[[0.0] * 4] * 2]
    # A ray from outside is 0 long whichever way it points (first_hit's promise); inside, the wall is 1.5 away.
    hits = first_hit(torch.tensor([[[2.5, 0.0], [0.5, 0.0]]]), torch.tensor([[[-1.0, 0.0], [1.0, 0.0]]]),
                     half_extent=ARENA)
    assert hits.tolist() == [[0.0, 1.5]]
    seen = line_of_sight(eye[:, :1], yaw[:, :1], torch.tensor([[[0.0, 0.0], [2.5, 0.0]]]), fov=math.pi,
                         reach=10.0, half_extent=ARENA)
    assert seen.tolist() == [[[False, True]]]  # the arena's centre lies behind its wall; its own point is seen


@pytest.mark.parametrize("kwargs, words", [
    (dict(rays=0), r"rays must be an int >= 1, got 0"), (dict(rays=-2), r"rays must be an int >= 1, got -2"),
    (dict(rays=2.0), r"rays must be an int >= 1, got 2.0"), (dict(reach=0.0), r"reach must be a finite number > 0"),
    (dict(reach=-1.0), r"reach must be a finite number > 0 \(metres\), got -1.0"),
    (dict(reach=math.nan), r"reach must be a finite number > 0"), (dict(reach=math.inf), r"reach must be a finite"),
])
def test_lidar_refuses_rays_and_reach_out_of_range(kwargs, words):
    with pytest.raises(ValueError, match=words):
        lidar(torch.zeros(1, 1, 2), torch.zeros(1, 1), half_extent=ARENA, **{"rays": 4, "reach": 5.0, **kwargs})


def test_line_of_sight_refuses_a_reach_that_is_not_positive():
    for reach in (0.0, -1.0, math.nan):
        with pytest.raises(ValueError, match=r"reach must be a number > 0"):
            line_of_sight(torch.zeros(1, 1, 2), torch.zeros(1, 1), torch.ones(1, 1, 2), fov=1.0, reach=reach,
                          half_extent=ARENA)


def test_a_negative_circle_radius_is_refused():
    circles = Circles(torch.tensor([[[0.5, 0.0]]]), torch.tensor([[-0.25]]), torch.tensor([[True]]))
    with pytest.raises(ValueError, match=r"circles.radius must be >= 0 \(metres\), got a minimum of -0.25"):
        first_hit(torch.zeros(1, 1, 2), torch.tensor([[[1.0, 0.0]]]), half_extent=ARENA, circles=circles)
    with pytest.raises(ValueError, match=r"circles.radius must be >= 0"):
        line_of_sight(torch.zeros(1, 1, 2), torch.zeros(1, 1), torch.ones(1, 1, 2), fov=1.0, reach=5.0,
                      half_extent=ARENA, circles=circles)
    with pytest.raises(ValueError, match=r"circles.radius must be >= 0"):
        lidar(torch.zeros(1, 1, 2), torch.zeros(1, 1), rays=4, reach=5.0, half_extent=ARENA, circles=circles)


def test_a_target_at_the_eye_is_seen_whatever_the_yaw():
    yaws = torch.linspace(-math.pi, math.pi, 9)[None]  # [1, 9]
    eye = torch.tensor([0.3, -0.2]).expand(1, 9, 2)
    seen = line_of_sight(eye, yaws, torch.tensor([[[0.3, -0.2]]]), fov=math.pi / 2, reach=5.0, half_extent=ARENA)
    assert seen.tolist() == [[[True]] * 9]
