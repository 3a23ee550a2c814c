"""Every description under urdf/ loads in PyBullet and Pinocchio, agrees between them, and is stable."""

import importlib.util
import math
import sys
import xml.etree.ElementTree as ET

import numpy as np
import pinocchio as pin
import pybullet as p
import pytest

from robotdemo.assets import ARM_JOINTS, ROBOT_URDF, TOOL_FRAME, all_urdfs, urdf_path, urdf_root
from robotdemo.errors import AssetError
from robotdemo.sim import SimConfig, Simulator, validate_urdf

ROBOTS = [path for path in all_urdfs() if ET.parse(path).getroot().find("joint[@type='revolute']") is not None]


def test_committed_files_match_generator():
    spec = importlib.util.spec_from_file_location("urdf_generate", urdf_root() / "generate.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules["urdf_generate"] = module  # dataclasses look their module up while the class is built
    spec.loader.exec_module(module)
    for rel, text in module.render_all().items():
        assert (urdf_root() / rel).read_text() == text, f"{rel} differs from urdf/generate.py output; rerun it"


def test_there_are_robot_and_scene_files():
    names = {path.name for path in all_urdfs()}
    assert {"rm65b.urdf", "dg3f_lite.urdf", "rm65b_dg3f.urdf", "table.urdf", "floor.urdf"} <= names
    assert len(ROBOTS) == 3


@pytest.mark.parametrize("path", all_urdfs(), ids=lambda p: p.name)
def test_loads_in_pybullet_and_pinocchio(path):
    model = pin.buildModelFromUrdf(str(path))
    assert model.nframes > 1
    with Simulator() as sim:
        body = sim.load_urdf(path, fixed_base=True)
        assert p.getNumJoints(body, physicsClientId=sim.client) == len(ET.parse(path).getroot().findall("joint"))


@pytest.mark.parametrize("path", ROBOTS, ids=lambda p: p.name)
def test_forward_kinematics_agree(path):
    """Every link frame agrees within 1e-6 m / 1e-6 rad over 200 random in-limit configurations."""
    model = pin.buildModelFromUrdf(str(path))
    data = model.createData()
    rng = np.random.default_rng(0)
    with Simulator() as sim:
        body = sim.load_urdf(path, fixed_base=True)
        joints = [j for j in sim.joints(body) if j.kind == p.JOINT_REVOLUTE]
        for _ in range(200):
            q_by_name = {j.name: rng.uniform(j.lower_rad, j.upper_rad) for j in joints}
            sim.reset_joints(body, [j.index for j in joints], [q_by_name[j.name] for j in joints])
            q = pin.neutral(model)
            for name, value in q_by_name.items():
                q[model.joints[model.getJointId(name)].idx_q] = value
            pin.framesForwardKinematics(model, data, q)
            for j in sim.joints(body):
                state = sim.link_state(body, j.index)
                oMf = data.oMf[model.getFrameId(j.link_name, pin.BODY)]
                assert np.linalg.norm(state.position_m - oMf.translation) < 1e-6, j.link_name
                angle = np.linalg.norm(pin.log3(state.rotation.T @ oMf.rotation))
                assert angle < 1e-6, j.link_name


def test_arm_reach_is_610_mm():
    """Shoulder (joint 2 axis) to flange, stretched out: 256 + 210 + 144 mm; no configuration reaches further."""
    model = pin.buildModelFromUrdf(str(urdf_path(ROBOT_URDF)))
    data = model.createData()
    shoulder, flange = model.getJointId("joint2"), model.getFrameId("link6")

    def reach(q):
        pin.framesForwardKinematics(model, data, q)
        return np.linalg.norm(data.oMf[flange].translation - data.oMi[shoulder].translation)

    straight = reach(pin.neutral(model))
    assert abs(straight - 0.61) <= 0.02
    rng = np.random.default_rng(1)
    farthest = max(reach(rng.uniform(model.lowerPositionLimit, model.upperPositionLimit)) for _ in range(2000))
    assert farthest <= straight + 1e-9
    # the tool frame (pad centre) is further out, on the gripper
    assert model.existFrame(TOOL_FRAME)


def test_joint_limits_match_reference():
    model = pin.buildModelFromUrdf(str(urdf_path(ROBOT_URDF)))
    expected_deg = [178, 130, 135, 178, 128, 360]
    expected_effort = [60, 60, 30, 10, 10, 10]
    for name, lim, eff in zip(ARM_JOINTS, expected_deg, expected_effort):
        idx = model.joints[model.getJointId(name)].idx_q
        assert math.isclose(model.upperPositionLimit[idx], math.radians(lim), rel_tol=1e-6)
        assert math.isclose(model.effortLimit[idx], eff)
    total_arm = sum(model.inertias[model.getJointId(n)].mass for n in ARM_JOINTS[:-1])
    assert 4.0 < total_arm < 6.0  # links 1..5 from the reference (5.21 kg) plus the gripper hanging on link 6


def _step_random(sim, body, rng, seconds=2.0, around=None, spread=None):
    joints = [j for j in sim.joints(body) if j.kind == p.JOINT_REVOLUTE]
    idx = [j.index for j in joints]
    lo = np.array([j.lower_rad for j in joints])
    hi = np.array([j.upper_rad for j in joints])
    efforts = [j.effort_nm for j in joints]
    speeds = [j.velocity_radps for j in joints]
    steps_per_command = 250
    for k in range(int(seconds / sim.config.time_step_s)):
        if k % steps_per_command == 0:
            if around is None:
                target = rng.uniform(lo, hi)
            else:
                target = np.clip(around + rng.uniform(-spread, spread), lo, hi)
            sim.position_control(body, idx, target, efforts, speeds, position_gain=0.1)
        sim.step()
        if k % 50 == 0:
            q = sim.joint_positions(body, idx)
            assert np.all(q >= lo - 0.05) and np.all(q <= hi + 0.05)
            assert np.all(np.abs(sim.joint_velocities(body, idx)) < 3.0 * np.array(speeds)), "joint speed exploded"
            for cp in sim.all_contact_points():
                assert cp.distance_m > -0.005, f"interpenetration {cp.distance_m * 1000:.1f} mm"


@pytest.mark.parametrize("path", ROBOTS, ids=lambda p: p.name)
def test_each_robot_steps_2s_under_random_commands(path):
    rng = np.random.default_rng(2)
    with Simulator() as sim:
        body = sim.load_urdf(path, position_m=(0, 0, 1.0), fixed_base=True)
        _step_random(sim, body, rng)
        sim.check_state_finite()


def test_bad_urdf_gives_one_line_error(tmp_path):
    with pytest.raises(AssetError, match="missing.urdf: URDF file not found"):
        validate_urdf(tmp_path / "missing.urdf")
    bad = tmp_path / "broken.urdf"
    bad.write_text("<robot name='x'><link name='a'></robot>")
    with pytest.raises(AssetError, match=r"broken.urdf: malformed URDF \(XML error"):
        validate_urdf(bad)
    dangling = tmp_path / "dangling.urdf"
    dangling.write_text("<robot name='x'><link name='a'/><joint name='j' type='fixed'><parent link='a'/>"
                        "<child link='b'/></joint></robot>")
    with Simulator() as sim, pytest.raises(AssetError) as info:
        sim.load_urdf(dangling)
    assert "dangling.urdf" in str(info.value) and "\n" not in str(info.value)


@pytest.mark.parametrize("bad, message", [
    ('<mass value="heavy"/>', "<mass value='heavy'> needs 1 finite number >= 0"),
    ('<mass value="-1"/>', "<mass value='-1'> needs 1 finite number >= 0"),
    ('<mass value="nan"/>', "<mass value='nan'> needs 1 finite number >= 0"),
    ('<origin xyz="0 zero" rpy="0 0 0"/>', "<origin xyz='0 zero'> needs 3 finite numbers"),
])
def test_urdf_numbers_are_checked(tmp_path, bad, message):
    inertial = '<origin xyz="0 0 0" rpy="0 0 0"/><mass value="1"/>'
    inertial = inertial.replace('<mass value="1"/>', bad) if bad.startswith("<mass") else \
        inertial.replace('<origin xyz="0 0 0" rpy="0 0 0"/>', bad)
    path = tmp_path / "numbers.urdf"
    path.write_text(f"<robot name='x'><link name='a'><inertial>{inertial}"
                    "<inertia ixx='1' ixy='0' ixz='0' iyy='1' iyz='0' izz='1'/></inertial></link></robot>")
    with pytest.raises(AssetError) as info:
        validate_urdf(path)
    assert str(info.value) == f"{path}: malformed URDF ({message})"


def test_every_committed_urdf_passes_the_checks():
    paths = sorted(urdf_root().rglob("*.urdf"))
    assert len(paths) >= 5
    for path in paths:
        validate_urdf(path)


def test_simulation_config_is_deterministic():
    def run():
        with Simulator(SimConfig()) as sim:
            body = sim.load_urdf(urdf_path(ROBOT_URDF), fixed_base=True)
            _step_random(sim, body, np.random.default_rng(5), seconds=0.5)
            return sim.joint_positions(body, range(12))
    assert np.array_equal(run(), run())
