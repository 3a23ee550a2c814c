"""The gripper closes on a block resting on the table and lifts it 10 cm by friction alone."""

import numpy as np
import pybullet as p
import pytest

from robotdemo.assets import FLOOR_URDF, TABLE_URDF, urdf_path
from robotdemo.motion import DOWN, ArmMotion, hold, run_to_completion
from robotdemo.robot import MAX_GRASP_WIDTH_M, GripperPosture, Robot, hand_position_for_grasp
from robotdemo.sim import Simulator
from robotdemo.sorting import SortingConfig

TABLE_Z = 0.70


def _world_with_block(size_m, density_kg_m3=700.0):
    sim = Simulator()
    sim.load_urdf(urdf_path(FLOOR_URDF), fixed_base=True)
    sim.load_urdf(urdf_path(TABLE_URDF), fixed_base=True)
    robot = Robot(sim, (-0.45, 0.0, TABLE_Z), np.pi)
    block = sim.create_primitive("box", (size_m,) * 3, density_kg_m3 * size_m**3, (-0.2, 0.05, TABLE_Z + size_m / 2),
                                 (0, 0, 0, 1), (0.6, 0.4, 0.2, 1))
    sim.set_dynamics(block, lateralFriction=0.6, contactStiffness=3e4, contactDamping=200)
    sim.step(100)
    return sim, robot, block


@pytest.mark.parametrize("size_m", [0.040, 0.055, 0.070])
def test_lifts_block_by_friction(size_m):
    sim, robot, block = _world_with_block(size_m)
    with sim:
        motion = ArmMotion(robot)
        n_constraints_before = p.getNumConstraints(physicsClientId=sim.client)
        start, _ = sim.base_pose(block)
        opened = GripperPosture.pinch_width(min(size_m + 0.024, MAX_GRASP_WIDTH_M))
        robot.command_gripper(opened)
        opening = opened.q[0]
        above = motion.solve_hand(hand_position_for_grasp(start[:2], TABLE_Z + 0.08, opening, DOWN))
        at = motion.solve_hand(hand_position_for_grasp(start[:2], TABLE_Z + 0.01, opening, DOWN), q=above.q)
        assert above.success and at.success
        run_to_completion(motion.plan_path([above.q, at.q]))
        robot.command_gripper(GripperPosture.pinch_width(size_m - 0.006))
        hold(robot, 0.8)
        assert len(robot.finger_contacts(block)) >= 2
        lifted = motion.solve_hand(hand_position_for_grasp(start[:2], TABLE_Z + 0.115, opening, DOWN), q=at.q)
        move = motion.plan_path([lifted.q])
        run_to_completion(move)
        hold(robot, 0.5)
        end, _ = sim.base_pose(block)
        assert end[2] - start[2] >= 0.10, f"block rose {1000 * (end[2] - start[2]):.1f} mm"
        assert np.linalg.norm(end[:2] - start[:2]) < 0.01  # closing did not shove it aside
        # held by friction alone: no constraint was created, only finger contacts carry it
        assert p.getNumConstraints(physicsClientId=sim.client) == n_constraints_before
        assert not sim.contact_points(block, sim.body_ids()[1])  # off the table
        assert max(move.tracking_errors_rad) < 0.01


def test_pinch_width_matches_finger_geometry():
    """The inner faces of the thumb tip and of the finger tips stand the requested width apart."""
    sim, robot, block = _world_with_block(0.05)
    with sim:
        sim.remove_body(block)
        for width in (0.04, 0.055, 0.07):
            robot.command_gripper(GripperPosture.pinch_width(width))
            hold(robot, 0.6)
            faces = []
            for finger in range(3):
                state = sim.link_state(robot.body, robot.link_index[f"finger{finger}_tip"])
                faces.append(state.position_m + state.rotation @ np.array([0.008, 0.0, 0.01]))  # inner face centre
            closing = sim.link_state(robot.body, robot.link_index["finger0_tip"]).rotation[:, 0]
            for finger in (1, 2):
                assert abs(float(closing @ (faces[finger] - faces[0]))) == pytest.approx(width, abs=0.0015)
        with pytest.raises(ValueError, match="outside what the gripper can open"):
            GripperPosture.pinch_width(0.2)


def _open_and_lower_around(sim, robot, body, width_m, above_z_m):
    """Open the fingers for an object ``width_m`` across and lower the hand from ``above_z_m`` until the
    fingertips are 12 mm above the table, around ``body``. Returns (motion, the object's start position,
    the opened posture, the joint solution at the bottom)."""
    motion = ArmMotion(robot)
    start, _ = sim.base_pose(body)
    opened = GripperPosture.pinch_width(width_m + 0.024)
    robot.command_gripper(opened)
    above = motion.solve_hand(hand_position_for_grasp(start[:2], above_z_m, opened.q[0], DOWN))
    at = motion.solve_hand(hand_position_for_grasp(start[:2], TABLE_Z + 0.012, opened.q[0], DOWN), q=above.q)
    run_to_completion(motion.plan_path([above.q, at.q]))
    return motion, start, opened, at


@pytest.mark.parametrize("density_kg_m3", [8500.0, 100.0])
def test_block_is_carried_in_the_carry_step_mode(density_kg_m3):
    """A 50 mm block, brass-dense (1.06 kg) or foam-light (12.5 g), squeezed as the sorting robot squeezes it, is
    lifted and carried 15 cm sideways at the ``carry`` step (1 ms, friction cone, 50 solver iterations) without
    slipping in the fingers. (At 2 ms with pyramid friction a 7 g slab slipped out
    in the demo; at 2 ms with the cone, a brass cylinder.)"""
    size_m = 0.05
    sim, robot, block = _world_with_block(size_m, density_kg_m3=density_kg_m3)
    with sim:
        assert sim.mass_kg(block) >= sim.config.carry_step.min_held_mass_kg
        motion, start, opened, at = _open_and_lower_around(sim, robot, block, size_m, TABLE_Z + 0.08)
        # SortingConfig.grasp_effort_per_kg_nm x mass, at least the sorting robot's least squeeze
        effort_nm = max(4.0 * density_kg_m3 * size_m**3, SortingConfig().grasp_effort_nm)
        robot.command_gripper(GripperPosture.pinch_width(size_m - 0.006), effort_nm=effort_nm)
        hold(robot, 0.5)
        hand = robot.link_index["finger0_tip"]
        offset0 = sim.base_pose(block)[0] - sim.link_state(robot.body, hand).position_m
        assert sim.use_step_mode("carry", held_body=block) == "carry"
        assert sim.time_step_s == pytest.approx(0.001)
        assert p.getPhysicsEngineParameters(physicsClientId=sim.client)["numSolverIterations"] == 50
        lifted = motion.solve_hand(hand_position_for_grasp(start[:2], TABLE_Z + 0.10, opened.q[0], DOWN), q=at.q)
        aside = motion.solve_hand(hand_position_for_grasp(start[:2] + np.array([0.0, -0.15]), TABLE_Z + 0.10,
                                                          opened.q[0], DOWN), q=lifted.q)
        assert lifted.success and aside.success
        run_to_completion(motion.plan_path([lifted.q, aside.q]))
        hold(robot, 0.3)
        sim.use_step_mode("fine")
        end, _ = sim.base_pose(block)
        slip_m = np.linalg.norm(end - sim.link_state(robot.body, hand).position_m - offset0)
        assert end[2] - start[2] >= 0.08 and np.linalg.norm(end[:2] - start[:2]) >= 0.13
        assert slip_m < 0.005, f"the block slipped {1000 * slip_m:.1f} mm in the fingers"


def test_a_light_held_body_keeps_the_fine_step():
    """Fewer solver iterations resolve a light body squeezed between the heavy fingers less well (a 4 g block
    shifted 12 mm in the fingers at 50 iterations against 3 mm at 100), so under ``min_held_mass_kg`` the
    ``carry`` mode falls back to the fine step; without a held body, or for a heavier one, it applies."""
    size_m = 0.05
    sim, robot, light = _world_with_block(size_m, density_kg_m3=32.0)
    with sim:
        heavy = sim.create_primitive("box", (size_m, size_m, size_m), 1.0, (0.3, 0.3, TABLE_Z + 0.03), (0, 0, 0, 1),
                                     (0.5, 0.5, 0.5, 1))
        assert sim.mass_kg(light) < sim.config.carry_step.min_held_mass_kg <= sim.mass_kg(heavy)

        def iterations() -> int:
            return p.getPhysicsEngineParameters(physicsClientId=sim.client)["numSolverIterations"]

        assert sim.use_step_mode("carry", held_body=light) == "fine" == sim.step_mode
        assert iterations() == sim.config.solver_iterations
        assert sim.use_step_mode("carry", held_body=heavy) == "carry" == sim.step_mode
        assert iterations() == sim.config.carry_step.solver_iterations < sim.config.solver_iterations
        sim.use_step_mode("fine")
        assert sim.use_step_mode("carry") == "carry" and iterations() == sim.config.carry_step.solver_iterations


@pytest.mark.parametrize("diameter_m", [0.040, 0.050])
def test_upright_cylinder_is_pinched_where_the_fingers_meet_it(diameter_m):
    """The two fingers stand 13 mm off the pinch axis at their inner edges, so they meet an upright cylinder
    short of its diameter: closing to the diameter minus the squeeze barely loads them, closing to
    ``round_pinch_width`` minus the squeeze puts the thumb and both fingers on it and lifts it."""
    from robotdemo.robot import round_pinch_width

    assert round_pinch_width(diameter_m) < diameter_m - 0.003
    sim = Simulator()
    sim.load_urdf(urdf_path(FLOOR_URDF), fixed_base=True)
    table = sim.load_urdf(urdf_path(TABLE_URDF), fixed_base=True)
    sim.set_dynamics(table, lateralFriction=1.5)  # the sorting scene's anti-slip mat: the thumb cannot shove it
    robot = Robot(sim, (-0.45, 0.0, TABLE_Z), np.pi)
    height = 0.06
    cylinder = sim.create_primitive("cylinder", (diameter_m, diameter_m, height), 0.12,
                                    (-0.2, 0.05, TABLE_Z + height / 2), (0, 0, 0, 1), (0.6, 0.6, 0.6, 1))
    sim.set_dynamics(cylinder, lateralFriction=0.8, contactStiffness=3e4, contactDamping=200)
    sim.step(100)
    with sim:
        motion, start, opened, at = _open_and_lower_around(sim, robot, cylinder, diameter_m, TABLE_Z + 0.11)
        finger_links = {robot.link_index[f"finger{f}_{part}"] for f in (1, 2) for part in ("distal", "tip")}

        def finger_force_n() -> float:
            return sum(c.normal_force_n for c in robot.finger_contacts(cylinder) if c.link_a in finger_links)

        robot.command_gripper(GripperPosture.pinch_width(diameter_m - 0.006))
        hold(robot, 0.5)
        diameter_rule_n = finger_force_n()
        robot.command_gripper(GripperPosture.pinch_width(round_pinch_width(diameter_m) - 0.006))
        hold(robot, 0.5)
        assert finger_force_n() > max(5.0 * diameter_rule_n, 0.5)
        lifted = motion.solve_hand(hand_position_for_grasp(start[:2], TABLE_Z + 0.11, opened.q[0], DOWN), q=at.q)
        run_to_completion(motion.plan_path([lifted.q]))
        hold(robot, 0.3)
        assert sim.base_pose(cylinder)[0][2] - start[2] >= 0.08
