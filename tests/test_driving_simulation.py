"""
The faster simulation classes of ``sb3_dacerf.envs.driving.common.simulation`` give highway-env's answers: the same
closest lane, neighbours, conflict decisions, IDM decisions and collisions, and so the same episodes.
"""

import copy
import pickle
from unittest import mock

import numpy as np
import pytest

pytest.importorskip("highway_env")

from highway_env.road.lane import CircularLane, StraightLane
from highway_env.road.regulation import RegulatedRoad
from highway_env.road.road import Road, RoadNetwork
from highway_env.vehicle.behavior import IDMVehicle
from highway_env.vehicle.controller import ControlledVehicle
from highway_env.vehicle.kinematics import Vehicle

from sb3_dacerf.envs.driving.common import simulation
from sb3_dacerf.envs.driving.common.simulation import (
    FastIDMVehicle,
    FastRegulatedRoad,
    FastRoad,
    IndexedRoadNetwork,
    predict_constant_speed,
)
from sb3_dacerf.envs.driving.intersection import FirstComeRoad, IntersectionEnv
from sb3_dacerf.envs.driving.multilane import MultilaneEnv

SCENARIOS = [MultilaneEnv, IntersectionEnv]


class StockFirstComeRoad(RegulatedRoad):
    """The intersection's first-come right of way on highway-env's own ``RegulatedRoad``."""

    respect_priorities = staticmethod(FirstComeRoad.respect_priorities)


def stock_road(road, road_class=FastRoad):
    if road_class is FirstComeRoad:
        return StockFirstComeRoad(road.network, np_random=road.np_random, record_history=road.record_history)
    return road  # highway-env's Road or RegulatedRoad


def highway_env_classes():
    """Envs made and stepped inside run on highway-env's own road, lane network and IDM vehicle classes."""
    return mock.patch.multiple(simulation, fast_road=stock_road, fast_vehicle_class=lambda vehicle_class: vehicle_class)


def stepped(env_class, steps=40, seed=0, **config):
    """An env after ``steps`` steps of small random actions (traffic in motion, some of it in the junction)."""
    env = env_class(config=config)
    env.reset(seed=seed)
    rng = np.random.default_rng(seed)
    for _ in range(steps):
        _, _, terminated, truncated, _ = env.step(rng.uniform(env.action_space.low, env.action_space.high) * 0.3)
        if terminated or truncated:
            env.reset(seed=seed + 1)
    return env


def run_episodes(env, steps, seed):
    """Observations, rewards, flags and info of ``steps`` steps of random actions, with seeded resets."""
    rng = np.random.default_rng(seed)
    obs, _ = env.reset(seed=seed)
    trace = [obs]
    for i in range(steps):
        action = rng.uniform(env.action_space.low, env.action_space.high).astype(np.float32)
        obs, reward, terminated, truncated, info = env.step(action)
        trace.append((obs, reward, terminated, truncated, info["crashed"], info["is_success"], len(env.road.vehicles)))
        if terminated or truncated:
            obs, _ = env.reset(seed=seed + 1 + i)
            trace.append(obs)
    return trace


def assert_same_trace(a, b):
    assert len(a) == len(b)
    for step_a, step_b in zip(a, b, strict=True):
        if isinstance(step_a, tuple):
            np.testing.assert_array_equal(step_a[0], step_b[0])
            assert step_a[1:] == step_b[1:]
        else:
            np.testing.assert_array_equal(step_a, step_b)


@pytest.mark.parametrize("env_class", SCENARIOS)
def test_the_envs_run_on_the_fast_classes(env_class):
    for config, road_class in (
        [({}, FastRoad)]
        if env_class is MultilaneEnv
        else [
            ({}, FirstComeRoad),
            ({"right_of_way": "priority"}, FastRegulatedRoad),
        ]
    ):
        fast = env_class(config=config)
        fast.reset(seed=0)
        with highway_env_classes():
            stock = env_class(config=config)
            stock.reset(seed=0)
        assert type(fast.road) is road_class and type(fast.road.network) is IndexedRoadNetwork
        traffic = [v for v in fast.road.vehicles if v is not fast.vehicle]
        assert traffic and all(type(v) is FastIDMVehicle for v in traffic)
        # the reference of the comparisons below: highway-env's own classes
        expected = {FastRoad: Road, FirstComeRoad: StockFirstComeRoad, FastRegulatedRoad: RegulatedRoad}[road_class]
        assert type(stock.road) is expected and type(stock.road.network) is RoadNetwork
        assert all(type(v) is IDMVehicle for v in stock.road.vehicles if v is not stock.vehicle)


@pytest.mark.parametrize(
    "env_class, config, steps",
    [
        (MultilaneEnv, {}, 200),
        (MultilaneEnv, {"lanes_count": 4}, 100),
        (IntersectionEnv, {}, 200),
        (IntersectionEnv, {"right_of_way": "priority"}, 100),
    ],
)
def test_same_episodes_as_highway_env_classes(env_class, config, steps):
    """Step for step the same observations, rewards, flags and vehicle counts, across resets."""
    for density in ("normal", "dense"):
        fast_trace = run_episodes(env_class(density=density, config={**config, "duration": 8}), steps, seed=3)
        with highway_env_classes():
            stock_trace = run_episodes(env_class(density=density, config={**config, "duration": 8}), steps, seed=3)
        assert_same_trace(fast_trace, stock_trace)
        # the traces cover episode ends, not only running traffic
        assert any(isinstance(step, tuple) and (step[2] or step[3]) for step in fast_trace)


@pytest.mark.parametrize("env_class", SCENARIOS)
def test_closest_lane_is_highway_env_s(env_class):
    network = stepped(env_class, steps=0).road.network
    rng = np.random.default_rng(0)
    lanes = network.lanes_list()
    positions, headings = [], []
    # points on and around every lane (lane ends and the junction's shared lane starts are ties), any heading
    for lane in lanes:
        for s in np.linspace(-5.0, lane.length + 5.0, 25):
            for lateral in (0.0, 1.0, -2.5, 6.0):
                positions.append(lane.position(s, lateral))
                headings.append(lane.heading_at(s) + rng.choice([0.0, 0.3, -1.0, np.pi, rng.uniform(-4, 4)]))
    positions += list(rng.uniform(-150, 150, size=(500, 2)))
    headings += list(rng.uniform(-np.pi, np.pi, size=500))
    for position, heading in zip(positions, headings, strict=True):
        assert network.get_closest_lane_index(position, heading) == RoadNetwork.get_closest_lane_index(network, position, heading)
        assert network.get_closest_lane_index(position) == RoadNetwork.get_closest_lane_index(network, position)


def test_closest_lane_of_a_position_that_is_not_finite_is_highway_env_s():
    network = stepped(IntersectionEnv, steps=0).road.network
    for position, heading in (([np.nan, 3.0], 0.0), ([2.0, np.inf], None), ([2.0, -30.0], np.nan)):
        position = np.array(position)
        with np.errstate(invalid="ignore"):  # highway-env's own search warns about these
            assert network.get_closest_lane_index(position, heading) == RoadNetwork.get_closest_lane_index(
                network, position, heading
            )


def test_remembered_lane_coordinates_are_the_lane_s():
    network = stepped(IntersectionEnv, steps=0).road.network
    rng = np.random.default_rng(1)
    for lane in network.lanes_list():
        base = type(lane).__mro__[2]  # the highway-env lane class after the remembering mixin
        assert base in (StraightLane, CircularLane)
        for position in [*rng.uniform(-60, 60, size=(20, 2)), np.array([0.0, -0.0]), np.array([-0.0, 0.0])]:
            for _ in range(2):  # computed, then remembered
                assert lane.local_coordinates(position) == base.local_coordinates(lane, position)
            assert lane.local_coordinates(list(position)) == base.local_coordinates(lane, np.array(position))
        # positions equal but for the sign of a zero are remembered apart
        signs = [np.copysign(1.0, c) for c in lane.local_coordinates(np.array([0.0, -0.0]))]
        assert signs == [np.copysign(1.0, c) for c in base.local_coordinates(lane, np.array([0.0, -0.0]))]


@pytest.mark.parametrize("env_class", SCENARIOS)
def test_neighbours_are_highway_env_s(env_class):
    compared = found = 0
    for seed in range(3):
        env = stepped(env_class, steps=30 + 20 * seed, seed=seed)
        road = env.road
        lane_indexes = [index for index in road.network.lanes_dict() if env_class is MultilaneEnv or index[0].startswith("ir")]
        lane_indexes += [None]  # the vehicle's own lane
        road._lane_coordinates = {}  # as during Road.act()
        try:
            for vehicle in road.vehicles:
                for lane_index in lane_indexes:
                    fast = road.neighbour_vehicles(vehicle, lane_index)
                    assert fast == Road.neighbour_vehicles(road, vehicle, lane_index), (vehicle, lane_index)
                    compared += 1
                    found += sum(v is not None for v in fast)
        finally:
            road._lane_coordinates = None
    assert compared > 100 and found > 20


def compare_conflict_decisions(road):
    """Every pair's conflict decision, checked against highway-env's, as during ``enforce_road_rules()``."""
    decisions = []
    road._predictions = {}
    try:
        for i, v1 in enumerate(road.vehicles):
            for v2 in road.vehicles[i + 1 :]:
                fast = road.is_conflict_possible(v1, v2)
                assert fast == bool(RegulatedRoad.is_conflict_possible(v1, v2)), (v1, v2)
                decisions.append(fast)
    finally:
        road._predictions = None
    return decisions


def test_conflict_decisions_are_highway_env_s():
    decisions = []
    for seed in range(2):
        env = IntersectionEnv(density="dense", config={"duration": 12})
        env.reset(seed=seed)
        rng = np.random.default_rng(seed)
        for step in range(100):
            _, _, terminated, truncated, _ = env.step(rng.uniform(env.action_space.low, env.action_space.high))
            if terminated or truncated:
                env.reset(seed=seed + step)
            if step % 4 == 0:
                decisions += compare_conflict_decisions(env.road)
        # an ego that crashed and is about to be moved by an impact rolls out differently
        env.vehicle.crashed, env.vehicle.impact = True, np.array([0.4, -0.2])
        decisions += compare_conflict_decisions(env.road)
    assert sum(decisions) >= 5 and not all(decisions)


def test_ego_prediction_without_the_road_is_highway_env_s():
    env = stepped(IntersectionEnv, steps=25)
    ego = env.vehicle
    times = np.arange(0.25, 3, 0.25)
    for crashed, impact in ((False, None), (True, np.array([0.3, 0.1]))):
        ego.crashed, ego.impact = crashed, impact
        positions, headings = predict_constant_speed(ego, times)
        expected_positions, expected_headings = Vehicle.predict_trajectory_constant_speed(ego, times)
        np.testing.assert_array_equal(positions, expected_positions)
        assert headings == expected_headings
    assert ego.road is env.road  # the vehicle itself is left on its road


@pytest.mark.parametrize("env_class", SCENARIOS)
def test_idm_decisions_are_highway_env_s(env_class):
    compared = 0
    for seed in range(3):
        env = stepped(env_class, steps=25 + 15 * seed, seed=seed)
        fast_road, stock_road = copy.deepcopy(env.road), copy.deepcopy(env.road)
        for fast, stock in zip(fast_road.vehicles, stock_road.vehicles, strict=True):
            if type(fast) is not FastIDMVehicle:
                continue
            for lane_index in {fast.lane_index, fast.target_lane_index}:
                assert fast.steering_control(lane_index) == ControlledVehicle.steering_control(stock, lane_index)
            for front in fast_road.vehicles[:6]:
                stock_front = stock_road.vehicles[fast_road.vehicles.index(front)]
                assert fast.acceleration(fast, front) == IDMVehicle.acceleration(stock, stock, stock_front)
            assert fast.acceleration(None) == IDMVehicle.acceleration(stock, None)
            fast.act()
            IDMVehicle.act(stock)
            assert fast.action == stock.action
            assert fast.target_lane_index == stock.target_lane_index
            compared += 1
    assert compared > 10


def test_collisions_are_highway_env_s():
    env = stepped(IntersectionEnv, steps=20)
    road = env.road
    # put two traffic vehicles on top of the ego and one next to another, then step both kinds of road
    others = [v for v in road.vehicles if v is not env.vehicle]
    others[0].position = env.vehicle.position + np.array([1.0, 0.5])
    others[1].position = others[2].position + np.array([0.0, 3.0])
    others[3].check_collisions = False
    fast, stock = copy.deepcopy(road), copy.deepcopy(road)
    fast.step(0.1)
    Road.step(stock, 0.1)
    assert [v.crashed for v in fast.vehicles] == [v.crashed for v in stock.vehicles]
    assert sum(v.crashed for v in fast.vehicles) >= 2
    for v_fast, v_stock in zip(fast.vehicles, stock.vehicles, strict=True):
        np.testing.assert_array_equal(v_fast.position, v_stock.position)
        assert (v_fast.impact is None and v_stock.impact is None) or np.array_equal(v_fast.impact, v_stock.impact)


@pytest.mark.parametrize("env_class", SCENARIOS)
def test_fast_env_pickles_and_steps_on_the_same(env_class):
    env = stepped(env_class, steps=10)
    copied = pickle.loads(pickle.dumps(env))
    action = np.zeros(2, dtype=np.float32)
    for _ in range(20):
        a, b = env.step(action), copied.step(action)
        np.testing.assert_array_equal(a[0], b[0])
        assert a[1:4] == b[1:4]
        if a[2] or a[3]:
            break
