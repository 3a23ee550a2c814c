"""The sorting state machine, stepped tick by tick: a whole episode, each injected fault and its recovery,
determinism.

The classifier here is a stand-in that reads the record's ground-truth label (the labels ride along in every
emulated record): it exercises the robot side only, never the perception.
"""

import dataclasses

import numpy as np
import pybullet as p
import pytest

from controllers.trajectory import TrajectoryError

from perception.materials import default_catalogue
from perception.streams import MODALITIES, StrokeRecord
from robotdemo.classifier import Classification, average_classifications, decide_zone
from robotdemo.motion import DOWN
from robotdemo.scene import Scene, SceneConfig
from robotdemo.sorting import FaultInjector, RestingGeometry, SortingConfig, SortingMachine, State, plan_stroke

CATEGORIES = default_catalogue().categories
PER_OBJECT = [State.APPROACH, State.STROKE, State.CLASSIFY, State.PRE_GRASP, State.GRASP, State.LIFT,
              State.TRANSPORT, State.PLACE, State.RELEASE, State.RETREAT]
"""The states an object goes through without faults (SELECT_OBJECT picks it and moves on in the same tick)."""


class OracleClassifier:
    """Stand-in: the record's true category at 0.94, gate weights uniform over the modalities present.
    Keeps every record it was given."""

    def __init__(self) -> None:
        self.records: list[StrokeRecord] = []

    def __call__(self, record: StrokeRecord) -> Classification:
        self.records.append(record)
        probs = {c: (0.94 if c == record.category else 0.01) for c in CATEGORIES}
        present = record.present
        return Classification(category=record.category, confidence=probs[record.category], probabilities=probs,
                              gate_weights={m: (1.0 / len(present) if m in present else 0.0) for m in MODALITIES},
                              modalities_present=present)


def _run(scene_config: SceneConfig, faults: FaultInjector = FaultInjector(), seed: int = 0,
         config: SortingConfig = SortingConfig(), max_ticks: int = 40_000):
    """Step a machine to DONE, one tick per call, watching it. Returns (machine, classifier, per-object state
    sequences, stroke phases seen, final poses, true zones, whether every step advanced the physics exactly one
    control tick, the whole sequence of states, the physics step modes seen per (state, object name), each
    object's mass in kg)."""
    classifier = OracleClassifier()
    with Scene(scene_config) as scene:
        n_constraints = p.getNumConstraints(physicsClientId=scene.sim.client)
        machine = SortingMachine(scene, classifier, config, seed=seed, faults=faults)
        sequences: dict[str, list[State]] = {}
        states = [machine.state]
        phases: set = set()
        step_modes: dict[tuple[State, str | None], set[str]] = {}
        one_tick = True
        for _ in range(max_ticks):
            time_before = scene.sim.time_s
            ticked, name = machine.state, machine.current_object.name if machine.current_object else None
            state = machine.step()
            step_modes.setdefault((ticked, name), set()).add(scene.sim.step_mode)
            one_tick &= abs(scene.sim.time_s - time_before - machine.dt) < 1e-9
            if states[-1] is not state:
                states.append(state)
            if machine.current_object is not None:
                seq = sequences.setdefault(machine.current_object.name, [])
                if not seq or seq[-1] is not state:
                    seq.append(state)
            if machine.stroke_phase is not None:
                phases.add(machine.stroke_phase.value)
            if machine.done:
                break
        assert machine.done, f"not done after {max_ticks} ticks: {machine.last_event}"
        assert p.getNumConstraints(physicsClientId=scene.sim.client) == n_constraints  # friction only
        poses = {o.name: np.concatenate(scene.object_pose(o)) for o in scene.objects}
        zones = {o.name: scene.zone_for(o.combustible).name for o in scene.objects}
        masses = {o.name: scene.sim.mass_kg(o.body) for o in scene.objects}
    return machine, classifier, sequences, phases, poses, zones, one_tick, states, step_modes, masses


@pytest.fixture(scope="module")
def episode():
    return _run(SceneConfig(n_objects=3, seed=0))


def test_episode_steps_through_every_state_to_done(episode):
    machine, classifier, sequences, phases, poses, true_zones, one_tick, states, _, _ = episode
    assert one_tick, "a step advanced the physics by other than one control tick"
    assert machine.state is State.DONE and machine.last_event.state is State.DONE
    assert states == [State.SELECT_OBJECT] + (PER_OBJECT + [State.SELECT_OBJECT]) * 3 + [State.DONE], \
        [s.value for s in states]
    assert len(sequences) == 3 and all(seq == PER_OBJECT for seq in sequences.values())
    assert {"press", "settle", "slide", "lift"} <= phases
    for name, d in machine.decisions.items():
        assert d.success, (name, d.failure_reason)
        assert d.zone_reached == d.target_zone == true_zones[name]
        assert d.predicted_category == d.true_category and d.strokes_taken == 1 and d.grasp_attempts == 1
        assert d.start_time_s < d.end_time_s
        # the pad felt the surface's kinetic friction while sliding (Coulomb in the simulator)
        kinetic = next(o.spec for o in machine.scene.objects if o.name == name).material.friction_kinetic
        assert d.measured_friction == pytest.approx(kinetic, rel=0.05)
    assert machine.grasp_failures == 0
    assert len(classifier.records) == 3


def test_physics_step_modes_follow_the_states(episode):
    """Stroking is simulated at the fine step (100 solver iterations), the arm moving with nothing in hand at the
    free step, and grasping to releasing at the carry step (50 iterations), except for objects lighter than the
    carry step's ``min_held_mass_kg``, which are held at the fine step."""
    machine, step_modes, masses = episode[0], episode[-2], episode[-1]
    min_mass_kg = machine.sim.config.carry_step.min_held_mass_kg
    assert max(masses.values()) >= min_mass_kg
    for (state, name), modes in step_modes.items():
        if state is State.STROKE:
            assert modes == {"fine", "free"}, (name, modes)  # the free step only while hovering, untouched
        elif state in (State.GRASP, State.LIFT, State.TRANSPORT, State.PLACE, State.RELEASE):
            assert modes == {"carry" if masses[name] >= min_mass_kg else "fine"}, (state, name, masses[name], modes)
        elif state in (State.APPROACH, State.PRE_GRASP, State.RETREAT):
            assert modes == {"free"}, (state, name, modes)


def test_events_are_named_records(episode):
    machine = episode[0]
    ticks = [e.tick for e in machine.events]
    assert ticks == sorted(ticks)
    stroke_events = [e for e in machine.events if e.state is State.STROKE and "phase slide" in e.message]
    assert len(stroke_events) == 3 and all(e.object_name for e in stroke_events)
    # an event carries the tick it happened in: the simulated time before or after that tick's physics
    assert all(0.3 + e.tick * 0.004 - 1e-9 <= e.time_s <= 0.3 + (e.tick + 1) * 0.004 + 1e-9 for e in machine.events)


@pytest.fixture(scope="module")
def faulty_episode():
    """Two objects: a reachable one with three faults injected (a sensor dropping out, a first classification
    of low confidence, a first grasp too weak to hold) and one out of the arm's reach."""
    scene_config = SceneConfig(n_objects=2, seed=19, object_region_m=(-0.28, 0.40, -0.05, 0.05), max_reach_m=1.0)
    with Scene(scene_config) as scene:
        far = max(scene.objects, key=lambda o: o.spec.xy_m[0])
        near = min(scene.objects, key=lambda o: o.spec.xy_m[0])
        assert far.spec.xy_m[0] > 0.25 and near.spec.xy_m[0] < -0.15  # the seed gives one of each
        names = (near.name, far.name)
    faults = FaultInjector(drop_modalities=("sound",), low_confidence_strokes=1, weak_grasp_attempts=1,
                           objects=(names[0],))
    return (*_run(scene_config, faults), names)


def test_unreachable_object_is_skipped_with_the_reason(faulty_episode):
    machine, names = faulty_episode[0], faulty_episode[-1]
    d = machine.decisions[names[1]]
    assert not d.success and d.failure_reason.startswith("unreachable: IK failed")
    assert d.strokes_taken == 0 and d.grasp_attempts == 0 and d.predicted_category is None


def test_sensor_dropout_is_classified_with_the_rest(faulty_episode):
    machine, classifier, names = faulty_episode[0], faulty_episode[1], faulty_episode[-1]
    assert classifier.records and all(r.stream("sound") is None for r in classifier.records)
    d = machine.decisions[names[0]]
    assert "sound" not in d.trusted_sensors and "sound" not in d.modalities_present
    assert d.trusted_sensors and set(d.trusted_sensors) <= {"normal", "friction", "accel"}
    assert d.gate_weights["sound"] == 0.0


def test_low_confidence_strokes_again_at_another_spot(faulty_episode):
    machine, classifier, names = faulty_episode[0], faulty_episode[1], faulty_episode[-1]
    d = machine.decisions[names[0]]
    assert d.strokes_taken == 2 and len(classifier.records) == 2
    starts = [r.meta for r in classifier.records]
    assert starts[0]["stroke"] == 0 and starts[1]["stroke"] == 1
    assert any("stroking again at another spot" in e.message for e in machine.events)
    assert d.predicted_category == d.true_category  # averaged: the flattened first stroke keeps the ranking
    assert 0.5 < d.confidence < 0.94


def test_weak_grasp_slips_and_is_retried(faulty_episode):
    machine, sequences, true_zones, names = faulty_episode[0], faulty_episode[2], faulty_episode[5], faulty_episode[-1]
    d = machine.decisions[names[0]]
    assert d.grasp_attempts == 2, [e.message for e in machine.events]
    assert any("retrying the grasp" in e.message for e in machine.events)
    assert d.success and d.zone_reached == true_zones[names[0]]
    assert sequences[names[0]].count(State.GRASP) == 2 and machine.grasp_failures == 1


def test_state_over_its_time_budget_fails_the_object_and_goes_on():
    scene_config = SceneConfig(n_objects=1, seed=4)
    faults = FaultInjector(time_budget_s={State.LIFT: 0.05})
    first = _run(scene_config, faults, seed=7)
    machine, sequences = first[0], first[2]
    (d,) = machine.decisions.values()
    assert not d.success and d.failure_reason == "lift exceeded its time budget of 0.05 s"
    (seq,) = sequences.values()
    assert seq[seq.index(State.LIFT) + 1] is State.RETREAT and machine.done
    # determinism: the same seed gives the same decisions and the same final poses
    second = _run(scene_config, faults, seed=7)
    assert second[0].decisions == machine.decisions
    for name, pose in first[4].items():
        np.testing.assert_allclose(second[4][name], pose, atol=1e-9)


def test_a_move_cut_short_is_taken_over_within_the_acceleration_limits():
    """TRANSPORT over its budget cuts the carrying move short with the arm at speed. The tick of the fault brakes
    it, and the retreat's move starts from the command's velocity and acceleration, so over the whole run no
    planned command changes its joint velocities faster than the acceleration limits allow."""
    faults = FaultInjector(time_budget_s={State.TRANSPORT: 0.3})
    with Scene(SceneConfig(n_objects=1, seed=4)) as scene:
        machine = SortingMachine(scene, OracleClassifier(), SortingConfig(), seed=7, faults=faults)
        log: list[tuple[int, State, np.ndarray | None]] = []
        command_arm = scene.robot.command_arm

        def logged(q, qd=None, qdd=None):
            command_arm(q, qd, qdd)
            log.append((machine.tick, machine.state, None if qd is None else np.array(qd)))

        scene.robot.command_arm = logged
        machine.run(max_ticks=20_000)
        (d,) = machine.decisions.values()
        assert d.failure_reason == "transport exceeded its time budget of 0.3 s"
        a_max = np.array(machine.motion.limits.acceleration_radps2)
        cut = max(i for i, (_, state, _) in enumerate(log) if state is State.TRANSPORT)
        assert np.max(np.abs(log[cut][2])) > 0.3  # it was cut short at speed
        # the tick of the fault itself brakes (no tick holds a stale target), then the retreat takes over
        assert log[cut + 1][1] is State.RETREAT and log[cut + 1][2] is not None and log[cut + 1][0] == log[cut][0] + 1
        planned = [(tick, qd) for tick, _, qd in log if qd is not None]
        for (tick0, qd0), (tick1, qd1) in zip(planned, planned[1:]):
            assert np.all(np.abs(qd1 - qd0) <= a_max * machine.dt * (tick1 - tick0) * (1 + 1e-6) + 1e-9), tick1


def test_a_trajectory_that_cannot_be_planned_fails_the_object_not_the_run(monkeypatch):
    with Scene(SceneConfig(n_objects=1, seed=4)) as scene:
        machine = SortingMachine(scene, OracleClassifier(), SortingConfig(), seed=7)
        plan_path = machine.motion.plan_path

        def no_plan_in_pre_grasp(waypoints):
            if machine.state is State.PRE_GRASP:
                raise TrajectoryError("segment 0 -> 1 cannot be planned within the limits (Ruckig: test)")
            return plan_path(waypoints)

        monkeypatch.setattr(machine.motion, "plan_path", no_plan_in_pre_grasp)
        machine.run(max_ticks=20_000)
        (d,) = machine.decisions.values()
        assert machine.done and not d.success
        assert d.failure_reason == ("no trajectory within the joint limits in pre_grasp (segment 0 -> 1 cannot be "
                                    "planned within the limits (Ruckig: test))")


def test_a_safety_waypoint_without_ik_is_reported():
    """Coming from afar, the pad goes over the next object at travel height first (so as not to sweep through
    others); without an IK solution for that waypoint the machine says so in its events and goes straight
    there."""
    with Scene(SceneConfig(n_objects=2, seed=0)) as scene:
        machine = SortingMachine(scene, OracleClassifier(), SortingConfig(), seed=0)
        solve_pad = machine.motion.solve_pad
        travel_z = scene.table_top_z_m + machine.config.travel_height_m

        def no_travel_height(position_w, rotation_w=DOWN, q=None):
            result = solve_pad(position_w, rotation_w, q)
            if abs(position_w[2] - travel_z) < 1e-12:
                return dataclasses.replace(result, success=False, position_error_m=0.012)
            return result

        machine.motion.solve_pad = no_travel_height
        machine.run(max_ticks=40_000)
        messages = [e.message for e in machine.events]
        assert messages.count("no IK for the travel-height waypoint over it (residual 12.0 mm); going straight "
                              "there") == 2  # each object is reached from afar: from home, then from the first
        assert all(d.success for d in machine.decisions.values())


def test_average_classifications_decides_from_mean_probabilities():
    a = Classification("wood", 0.5, {"wood": 0.5, "metal": 0.4, "paper": 0.1}, {"sound": 1.0}, ("sound",))
    b = Classification("metal", 0.7, {"wood": 0.2, "metal": 0.7, "paper": 0.1}, {"sound": 0.5, "normal": 0.5},
                       ("sound", "normal"))
    mean = average_classifications([a, b])
    assert mean.category == "metal" and mean.confidence == pytest.approx(0.55)
    assert mean.gate_weights == {"sound": 0.75, "normal": 0.25}
    assert mean.modalities_present == ("sound", "normal")


def test_zone_follows_the_summed_probability_of_each_side():
    combustible = default_catalogue().combustible
    # wood is the single most probable category, but metal + stone together outweigh everything that burns
    spread = Classification("wood", 0.4, {"wood": 0.4, "metal": 0.35, "stone": 0.25}, {}, ("sound",))
    side = decide_zone(spread, combustible)
    assert not side.combustible and side.category == "metal"
    assert side.combustible_probability == pytest.approx(0.4) and side.confidence == pytest.approx(0.6)
    sure = Classification("paper", 0.9, {"paper": 0.9, "metal": 0.1}, {}, ("sound",))
    side = decide_zone(sure, combustible)
    assert side.combustible and side.category == "paper" and side.confidence == pytest.approx(0.9)


def test_pregrasp_height_clears_tall_neighbours():
    """The hand opens over an object above the tallest top near it: a 60 mm cylinder 12 cm from a 24 mm slab
    raises the slab's clearance height to its own top; a cylinder 30 cm away does not."""
    from perception.materials import contact_dynamics, sample_material
    from robotdemo.scene import ObjectSpec
    from robotdemo.sorting import clearance_height

    catalogue = default_catalogue()

    def spec(name, instance, shape, size, xy):
        sample = sample_material(catalogue.instance(instance), np.random.default_rng(0))
        body = "cylinder" if shape == "cylinder" else "box"
        return ObjectSpec(name=name, shape=shape, size_m=size, xy_m=xy, yaw_rad=0.0, material=sample,
                          dynamics=contact_dynamics(sample, size, body))

    slab = spec("slab", "silicone_rubber", "slab", (0.078, 0.049, 0.024), (-0.25, 0.0))
    near = spec("near", "acrylic", "cylinder", (0.04, 0.04, 0.06), (-0.13, 0.0))
    far = spec("far", "acrylic", "cylinder", (0.04, 0.04, 0.06), (-0.25, 0.30))
    for neighbour, tall_near in ((near, True), (far, False)):
        with Scene(SceneConfig(n_objects=0, seed=0), catalogue=catalogue, objects=[slab, neighbour]) as scene:
            top = scene.table_top_z_m
            clear = clearance_height(scene, scene.objects[0], SortingConfig().pregrasp_neighbour_radius_m)
            assert clear == pytest.approx(top + (0.06 if tall_near else 0.024), abs=2e-3)


def test_object_pushed_out_of_its_zone_after_placing_fails_with_the_reason():
    """The final tally looks at where each object rests at the end: one that was placed in its zone and later
    left it (here a box thrown at it once the robot is done with it) fails, and the report says why."""
    classifier = OracleClassifier()
    with Scene(SceneConfig(n_objects=1, seed=4)) as scene:
        machine = SortingMachine(scene, classifier, SortingConfig(), seed=0)
        obj = scene.objects[0]
        while machine.decisions[obj.name].end_time_s is None:
            machine.step()
        d = machine.decisions[obj.name]
        assert d.success and d.zone_reached == scene.zone_for(obj.combustible).name
        zone = scene.zone_for(obj.combustible)
        rest, _ = scene.object_pose(obj)
        start = rest + np.array([0.0, -0.06 * np.sign(zone.center_xy_m[1]), 0.0])  # from the table's centre side
        start[2] = scene.table_top_z_m + 0.015
        projectile = scene.sim.create_primitive("box", (0.03, 0.03, 0.03), 2.0, start, (0, 0, 0, 1), (1, 0, 0, 1))
        p.resetBaseVelocity(projectile, [0.0, 3.0 * np.sign(zone.center_xy_m[1]), 0.0],
                            physicsClientId=scene.sim.client)
        scene.sim.advance(1.0)  # the box strikes it before the machine's next tick
        machine.step()
        assert machine.done and scene.zone_of(obj) is None
        d = machine.decisions[obj.name]
        assert not d.success and d.zone_reached is None
        assert d.failure_reason == f"pushed out of the {zone.name} zone after it was placed"


def test_object_knocked_out_before_it_rests_fails_with_the_reason():
    """An object that leaves its zone between release and coming to rest (here a box thrown at it while the hand
    retreats) is not counted, and the report says where it came to rest."""
    classifier = OracleClassifier()
    with Scene(SceneConfig(n_objects=1, seed=4)) as scene:
        machine = SortingMachine(scene, classifier, SortingConfig(), seed=0)
        obj = scene.objects[0]
        zone = scene.zone_for(obj.combustible)
        while machine.state is not State.RETREAT:
            machine.step()
        rest, _ = scene.object_pose(obj)
        start = rest + np.array([0.0, -0.06 * np.sign(zone.center_xy_m[1]), 0.0])
        start[2] = scene.table_top_z_m + 0.015
        projectile = scene.sim.create_primitive("box", (0.03, 0.03, 0.03), 2.0, start, (0, 0, 0, 1), (1, 0, 0, 1))
        p.resetBaseVelocity(projectile, [0.0, 3.0 * np.sign(zone.center_xy_m[1]), 0.0],
                            physicsClientId=scene.sim.client)
        while machine.decisions[obj.name].end_time_s is None:
            machine.step()
        d = machine.decisions[obj.name]
        assert scene.zone_of(obj) is None and not d.success and d.zone_reached is None
        assert d.failure_reason == f"came to rest in no zone, not the {zone.name} zone"


@pytest.fixture(scope="module")
def tall_light_cylinder():
    """Seed 8's 99 g polycarbonate cylinder, 42 mm across and 60 mm tall (static friction 1.16 on the pad)."""
    with Scene(SceneConfig(n_objects=6, seed=8)) as scene:
        spec = next(o.spec for o in scene.objects if o.name == "object4_polycarbonate")
    assert spec.dynamics.mass_kg == pytest.approx(0.0995, abs=1e-3) and spec.size_m[2] == pytest.approx(0.060, abs=1e-3)
    return spec


def test_object_whose_every_stroke_wedges_is_classified_from_the_presses(tall_light_cylinder):
    """A stuck pad pushing the cylinder's top tips it about its leading edge, which raises the face into the
    pad: the force climbs past 20 N at the start of each slide and the stroke fails, at 1.5 N and on the
    0.5 N retries alike (at this seed's spots). The pad pressed and held the force each time, so the
    robot classifies what the presses felt rather than give up, and sorts the cylinder."""
    config = SortingConfig(stroke_force_n=(1.5, 1.5))
    with Scene(SceneConfig(n_objects=0, seed=0), objects=[tall_light_cylinder]) as scene:
        classifier = OracleClassifier()
        machine = SortingMachine(scene, classifier, config, seed=0)
        machine.run(max_ticks=20_000)
        d = machine.decisions[tall_light_cylinder.name]
        messages = [e.message for e in machine.events]
        failed = [m for m in messages if m.startswith("stroke failed")]
        assert len(failed) == 3 and all("above max_force_n" in m for m in failed)
        assert [m.split(",")[0] for m in messages if m.startswith("stroking:")] == \
            ["stroking: 1.50 N", "stroking: 0.50 N", "stroking: 0.50 N"]
        assert "classifying what the presses felt" in failed[-1]
        assert len(classifier.records) == 1 and d.strokes_taken == 3
        assert d.success and d.zone_reached == "combustible"


def test_slippery_heavy_block_is_squeezed_harder_by_the_friction_the_pad_measured():
    """Seed 3's 451 g PTFE block (kinetic friction 0.24): the stroke measures the friction, and the fingers'
    cap is the mass-based one times 0.5 / 0.24 (about 2.1); without the correction it is the mass-based one."""
    with Scene(SceneConfig(n_objects=6, seed=3)) as scene:
        spec = next(o.spec for o in scene.objects if o.name == "object4_ptfe")
    efforts = {}
    for reference in (0.5, 0.0):
        with Scene(SceneConfig(n_objects=0, seed=0), objects=[spec]) as scene:
            machine = SortingMachine(scene, OracleClassifier(), SortingConfig(grasp_reference_friction=reference),
                                     seed=0)
            while machine.state is not State.LIFT:
                machine.step()
                assert machine.tick < 10_000
            d = machine.decisions[spec.name]
            assert d.measured_friction == pytest.approx(spec.material.friction_kinetic, rel=0.05)
            efforts[reference] = scene.robot.gripper_effort_nm
    assert efforts[0.0] > 1.5  # the mass-based cap is above the robot's default 1.5 N m already
    assert efforts[0.5] / efforts[0.0] == pytest.approx(0.5 / spec.material.friction_kinetic, rel=0.05)


def test_max_slide_time_cuts_slow_strokes_short():
    """With ``stroke_max_slide_s`` a slow stroke is a short one: its slide lasts at most that long, or it is the
    controller's shortest (20 mm). The draws are the same with and without the cut."""
    geometry = RestingGeometry(center_m=np.array([-0.2, 0.0, 0.01]), height_m=0.02, long_axis=np.array([1.0, 0.0, 0.0]),
                               short_axis=np.array([0.0, 1.0, 0.0]), long_m=0.14, short_m=0.08, round_top=False,
                               curved_top=False)
    ranges = dict(stroke_speed_mps=(0.005, 0.05), stroke_length_m=(0.02, 0.06))
    cut, uncut = SortingConfig(stroke_max_slide_s=1.0, **ranges), SortingConfig(**ranges)
    shortened = 0
    for seed in range(40):
        a = plan_stroke(geometry, cut, np.random.default_rng(seed))
        b = plan_stroke(geometry, uncut, np.random.default_rng(seed))
        assert (a.speed_mps, a.target_force_n, a.direction_rad) == (b.speed_mps, b.target_force_n, b.direction_rad)
        assert a.length_m == pytest.approx(min(b.length_m, max(0.02, b.speed_mps * 1.0)))
        shortened += a.length_m < b.length_m - 1e-9
    assert shortened >= 10  # slow draws were cut
    with pytest.raises(ValueError, match="stroke_max_slide_s"):
        SortingConfig(stroke_max_slide_s=0.0)
