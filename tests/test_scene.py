"""The sorting scene: deterministic layout, physical materials, stable under random commands."""

import math

import numpy as np
import pytest

import pybullet as p

from perception.materials import contact_dynamics, default_catalogue, sample_material
from robotdemo.cli import main
from robotdemo.scene import ObjectSpec, Scene, SceneConfig, body_shape
from robotdemo.sim import SimConfig
from tests.test_urdf import _step_random


def test_same_seed_same_layout_and_state():
    def run(seed):
        with Scene(SceneConfig(n_objects=5, seed=seed)) as scene:
            scene.sim.step(200)
            return scene.summary(), [scene.object_pose(o)[0].tolist() for o in scene.objects]
    assert run(4) == run(4)
    assert run(4) != run(5)


def test_objects_placed_apart_on_table_outside_zones():
    for seed in range(5):
        with Scene(SceneConfig(n_objects=6, seed=seed)) as scene:
            specs = [o.spec for o in scene.objects]
            for i, a in enumerate(specs):
                for b in specs[i + 1:]:
                    assert math.dist(a.xy_m, b.xy_m) >= a.footprint_radius_m + b.footprint_radius_m
            for obj in scene.objects:
                pos, _ = scene.object_pose(obj)
                assert abs(pos[2] - (scene.table_top_z_m + obj.spec.size_m[2] / 2)) < 0.005  # resting, not sunk
                assert scene.zone_of(obj) is None
                # reachable: within the arm's 0.61 m of the shoulder, leaving room for the hand
                assert np.linalg.norm(pos[:2] - np.array(scene.config.robot_base_xy_m)) < 0.45


def test_material_sets_dynamics_and_mass():
    with Scene(SceneConfig(n_objects=6, seed=1)) as scene:
        for obj in scene.objects:
            info = p.getDynamicsInfo(obj.body, -1, physicsClientId=scene.sim.client)
            d = obj.spec.dynamics
            assert info[0] == pytest.approx(d.mass_kg)
            assert info[1] == pytest.approx(d.lateral_friction)
            volume = np.prod(obj.spec.size_m) * (math.pi / 4 if obj.spec.shape == "cylinder" else 1.0)
            assert d.mass_kg == pytest.approx(obj.spec.material.density_kg_m3 * volume, rel=1e-6)


def test_full_scene_steps_2s_under_random_arm_commands():
    """Random joint targets around the home posture (the arm must not be flung into the table at 60 N m)."""
    with Scene(SceneConfig(n_objects=6, seed=2)) as scene:
        home = scene.robot.arm_q()
        _step_random(scene.sim, scene.robot.body, np.random.default_rng(3), seconds=2.0,
                     around=np.concatenate([home, scene.robot.gripper_q()]), spread=0.3)
        scene.sim.check_state_finite()


def test_cli_scene_prints_objects(capsys):
    assert main(["scene", "--objects", "3", "--seed", "1", "--seconds", "0.1"]) == 0
    out = capsys.readouterr().out
    assert out.count("object") >= 3


def test_cli_reports_impossible_layout_in_one_line(capsys):
    assert main(["scene", "--objects", "40", "--seconds", "0"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("robotdemo: error: cannot place 40 objects") and "\n" not in err


def test_free_steps_keep_time_and_leave_resting_objects_at_rest():
    """The free mode (4 ms steps, for the arm moving with nothing in hand) advances the same simulated time in
    fewer steps, switching back and forth does not disturb objects at rest, and the fine mode is restored."""
    with Scene(SceneConfig(n_objects=4, seed=6)) as scene:
        sim = scene.sim
        before = {o.name: scene.object_pose(o)[0] for o in scene.objects}
        t0, steps0 = sim.time_s, sim.steps
        sim.use_step_mode("free")
        assert sim.time_step_s == pytest.approx(0.004)
        sim.advance(0.2)
        assert sim.steps - steps0 == 50 and sim.time_s == pytest.approx(t0 + 0.2)
        sim.use_step_mode("fine")
        sim.advance(0.1)
        assert sim.steps - steps0 == 150 and sim.time_s == pytest.approx(t0 + 0.3)
        for obj in scene.objects:
            assert np.linalg.norm(scene.object_pose(obj)[0] - before[obj.name]) < 2e-4
        with pytest.raises(ValueError, match="whole physics steps"):
            sim.advance(0.0005)
        with pytest.raises(ValueError, match="unknown step mode"):
            sim.use_step_mode("turbo")


@pytest.mark.parametrize("sleep_speed_mps", [0.005, None])
def test_resting_objects_sleep_and_wake_when_struck(sleep_speed_mps):
    """Objects left at rest for longer than Bullet's deactivation time fall asleep (if enabled) and stay put;
    a box thrown at one wakes it and knocks it aside just as it knocks an object that never slept."""
    with Scene(SceneConfig(n_objects=1, seed=3, shapes=("box",), object_sleep_speed_mps=sleep_speed_mps)) as scene:
        obj = scene.objects[0]
        sim = scene.sim
        rest, _ = scene.object_pose(obj)
        sim.advance(3.0)
        assert np.linalg.norm(scene.object_pose(obj)[0] - rest) < 2e-4
        if sleep_speed_mps is not None:  # asleep: a pushing force alone does not wake it (Bullet); contact does
            for _ in range(20):
                p.applyExternalForce(obj.body, -1, [0.0, 0.0, 100.0], rest.tolist(), p.WORLD_FRAME,
                                     physicsClientId=sim.client)
                sim.step()
            assert np.linalg.norm(scene.object_pose(obj)[0] - rest) < 2e-4
        z = scene.table_top_z_m + obj.spec.size_m[2] / 2
        start = rest + np.array([0.0, 0.12, 0.0])
        start[2] = z
        projectile = sim.create_primitive("box", (0.03, 0.03, 0.03), 0.5, start, (0, 0, 0, 1), (1, 0, 0, 1))
        p.resetBaseVelocity(projectile, [0.0, -1.5, 0.0], physicsClientId=sim.client)
        sim.advance(0.5)
        moved_m = np.linalg.norm(scene.object_pose(obj)[0][:2] - rest[:2])
        assert moved_m > 0.005, f"the struck object moved {1000 * moved_m:.1f} mm"


def _pushed_at_the_top(clamp: bool, force_n: float = 20.0, steps: int = 300) -> tuple[float, float]:
    """How far (m) and how much (deg) a box moves and tilts while pushed sideways at its top edge."""
    size = (0.04, 0.04, 0.06)
    material = sample_material(default_catalogue().instance("oak"), np.random.default_rng(0))
    spec = ObjectSpec(name="block", shape="box", size_m=size, xy_m=(-0.2, 0.0), yaw_rad=0.0, material=material,
                      dynamics=contact_dynamics(material, size, body_shape("box")))
    with Scene(SceneConfig(n_objects=0, seed=0), objects=[spec]) as scene:
        obj = scene.objects[0]
        if clamp:
            scene.clamp(obj)
        start, orientation = scene.object_pose(obj)
        for _ in range(steps):
            top, _ = scene.object_pose(obj)
            p.applyExternalForce(obj.body, -1, [force_n, 0.0, 0.0], (top + [0.0, 0.0, 0.03]).tolist(),
                                 p.WORLD_FRAME, physicsClientId=scene.sim.client)
            scene.sim.step()
        end, orientation_end = scene.object_pose(obj)
        tilt = np.degrees(2 * np.arccos(min(1.0, abs(float(np.dot(orientation, orientation_end))))))
        return float(np.linalg.norm(end - start)), float(tilt)


def test_clamped_sample_holds_under_a_push_that_moves_it_when_free():
    """The data set's fixture: a clamped block stays put (under 0.5 mm, 0.5 deg) under a 20 N push at its top
    edge that slides and tips the same block left free."""
    free_moved, free_tilt = _pushed_at_the_top(clamp=False)
    clamped_moved, clamped_tilt = _pushed_at_the_top(clamp=True)
    assert free_moved > 0.01 or free_tilt > 5.0
    assert clamped_moved < 5e-4 and clamped_tilt < 0.5


def test_clamped_sample_rests_on_the_clamp_alone():
    """``Scene.clamp``: the table, floor and zones no longer touch the sample, which neither sinks nor moves
    under gravity for a second (the fixed joint carries it). The robot still strokes it: see
    test_stroking's test of the data set's fixture."""
    material = sample_material(default_catalogue().instance("granite"), np.random.default_rng(1))
    size = (0.05, 0.05, 0.04)
    spec = ObjectSpec(name="block", shape="box", size_m=size, xy_m=(-0.2, 0.0), yaw_rad=0.3, material=material,
                      dynamics=contact_dynamics(material, size, body_shape("box")))
    with Scene(SceneConfig(n_objects=0, seed=0), objects=[spec]) as scene:
        obj = scene.objects[0]
        assert p.getContactPoints(scene.table, obj.body, physicsClientId=scene.sim.client)
        start, _ = scene.object_pose(obj)
        scene.clamp(obj)
        scene.sim.advance(1.0)
        end, _ = scene.object_pose(obj)
        client = scene.sim.client
        for body in (scene.floor, scene.table, *scene.zone_bodies):
            assert not p.getContactPoints(body, obj.body, physicsClientId=client)
        assert np.linalg.norm(end - start) < 1e-4


def test_solver_iterations_set_for_every_step_mode():
    config = SimConfig().with_solver_iterations(40)
    assert config.solver_iterations == config.free_step.solver_iterations == config.carry_step.solver_iterations == 40
    assert config.free_step.time_step_s == SimConfig().free_step.time_step_s
    assert config.carry_step.cone_friction == SimConfig().carry_step.cone_friction
    with pytest.raises(ValueError, match="solver iterations must be >= 1"):
        SimConfig().with_solver_iterations(0)
    with Scene(SceneConfig(n_objects=0, seed=0, sim=config)) as scene:
        for mode in ("fine", "free", "carry"):
            scene.sim.use_step_mode(mode)
            assert p.getPhysicsEngineParameters(physicsClientId=scene.sim.client)["numSolverIterations"] == 40


@pytest.mark.parametrize("shape", ["box", "cylinder"])
def test_a_pad_dragged_over_a_top_face_feels_a_steady_force(tmp_path, shape):
    # PyBullet's cylinder gave a sliding box one new contact point per step: a 3 N press dragged over its top
    # read 0.8-7.3 N (5th-95th percentile). Bodies now load with separating-axis features: a patch, as on a box.
    from robotdemo.sim import Simulator

    pad_urdf = tmp_path / "pad.urdf"
    pad_urdf.write_text('<?xml version="1.0"?><robot name="pad"><link name="pad"><inertial><mass value="0.05"/>'
                        '<inertia ixx="1e-6" iyy="1e-6" izz="1e-6" ixy="0" ixz="0" iyz="0"/></inertial><collision>'
                        '<geometry><box size="0.016 0.016 0.004"/></geometry></collision></link></robot>')
    height = 0.05
    with Simulator(SimConfig()) as sim:
        top = sim.create_primitive(shape, (0.06, 0.06, height), 0.0, (0, 0, height / 2), (0, 0, 0, 1), (1, 1, 1, 1))
        pad = sim.load_urdf(pad_urdf, (-0.012, 0.003, height + 0.002))
        for body in (top, pad):
            sim.set_dynamics(body, lateralFriction=0.6)
        drag = p.createConstraint(pad, -1, -1, -1, p.JOINT_POINT2POINT, [0, 0, 0], [0, 0, 0],
                                  [-0.012, 0.003, height + 0.002], physicsClientId=sim.client)
        forces = []
        for k in range(1000):
            x = -0.012 + 0.03 * max(0, k - 200) * 1e-3  # 30 mm/s after 0.2 s
            p.changeConstraint(drag, [x, 0.003, height + 0.0015], maxForce=3.0, physicsClientId=sim.client)
            sim.step()
            if k > 250:
                forces.append(sum(c.normal_force_n for c in sim.contact_points(pad, top)))
    low, high = np.percentile(forces, [5, 95])
    assert low > 0.9 * np.median(forces) and high < 1.1 * np.median(forces), (low, high)


def test_a_cylinder_sized_with_numpy_numbers_keeps_its_mass():
    # its URDF is written as text: np.float64(0.2) used to read as mass 0, a static body
    from robotdemo.sim import Simulator

    with Simulator(SimConfig()) as sim:
        body = sim.create_primitive("cylinder", np.array([0.05, 0.05, 0.08]), np.float64(0.2), np.zeros(3),
                                    (0, 0, 0, 1), np.ones(4))
        assert p.getDynamicsInfo(body, -1, physicsClientId=sim.client)[0] == pytest.approx(0.2)
