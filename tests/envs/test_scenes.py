"""Scenes from seeds: splits, config validation, determinism, geometry and placement invariants.

Everything here runs the real generator (``generate_scene``) on the real split seeds.
"""

from __future__ import annotations

import itertools
from collections import Counter

import numpy as np
import pytest
from highway_env import utils
from highway_env.vehicle.objects import Obstacle

from pe_rlhf.envs import (DrivingConfig, TEST_SEEDS, TRAIN_SEEDS, VALIDATION_SEEDS, make_gym_env, parse_seeds,
                          scene_seeds)
from pe_rlhf.envs.blocks import BLOCK_TYPES
from pe_rlhf.envs.scene import EGO_START, generate_scene

ALL_SEEDS = TRAIN_SEEDS + VALIDATION_SEEDS + TEST_SEEDS


@pytest.fixture(scope="module")
def scenes() -> dict:
    """Every split scene under the default config, generated once."""
    config = DrivingConfig()
    return {seed: generate_scene(seed, config) for seed in ALL_SEEDS}


def _lane_geometry(network, s_fractions=(0.0, 0.3, 0.7, 1.0)) -> dict:
    """Positions and headings of every lane of ``network`` at a few fractions of its length."""
    out = {}
    for _from, to_dict in network.graph.items():
        for _to, lanes in to_dict.items():
            for i, lane in enumerate(lanes):
                out[(_from, _to, i)] = np.array(
                    [[*lane.position(f * lane.length, 0.0), lane.heading_at(f * lane.length)] for f in s_fractions]
                )
    return out


def _route_s(route, lane_index, position) -> float:
    """Route progress [m] of a world position on a route lane."""
    k = route.segment_index(lane_index)
    assert k is not None
    return route.project(np.asarray(position, float), k)[1]


# -- splits ------------------------------------------------------------------------------


def test_splits_are_50_scenes_each_and_pairwise_disjoint():
    splits = (TRAIN_SEEDS, VALIDATION_SEEDS, TEST_SEEDS)
    assert all(len(s) == 50 and len(set(s)) == 50 for s in splits)
    assert len(set(TRAIN_SEEDS) | set(VALIDATION_SEEDS) | set(TEST_SEEDS)) == 150
    assert scene_seeds("train") == TRAIN_SEEDS
    assert scene_seeds("validation") == VALIDATION_SEEDS
    assert scene_seeds("test") == TEST_SEEDS
    with pytest.raises(ValueError, match="dev"):
        scene_seeds("dev")


def test_parse_seeds_ranges_and_lists():
    seeds = parse_seeds("2000-2049")
    assert len(seeds) == 50 and seeds[0] == 2000 and seeds[-1] == 2049
    assert seeds == tuple(range(2000, 2050))
    assert parse_seeds("3,5") == (3, 5)
    assert parse_seeds("7") == (7,)
    assert parse_seeds("4-4") == (4,)
    assert parse_seeds(" 1 , 2 ,3 ") == (1, 2, 3)


@pytest.mark.parametrize("text", ["abc", "1-", "-", "5-3", "1-2-3", "3,x", "1.5", "a-b"])
def test_parse_seeds_rejects_bad_strings(text):
    with pytest.raises(ValueError, match="bad seeds"):
        parse_seeds(text)


# -- config validation ---------------------------------------------------------------------


@pytest.mark.parametrize(
    ("kwargs", "field"),
    [
        ({"traffic_density": -1}, "traffic_density"),
        ({"traffic_density": 6}, "traffic_density"),
        ({"obstacle_density": -0.1}, "obstacle_density"),
        ({"truck_fraction": 1.5}, "truck_fraction"),
        ({"side_traffic_probability": -0.2}, "side_traffic_probability"),
        ({"lanes": 7}, "lanes"),
        ({"lanes": 1}, "lanes"),
        ({"min_blocks": 5, "max_blocks": 4}, "min_blocks"),
        ({"block_types": ("spaceship",)}, "block_types"),
        ({"block_types": ()}, "block_types"),
        ({"horizon": 0}, "horizon"),
        ({"simulation_frequency": 15, "policy_frequency": 10}, "simulation_frequency"),
        ({"policy_frequency": 0}, "simulation_frequency"),
        ({"lidar_beams": 0}, "lidar_beams"),
        ({"lidar_range": 0.0}, "lidar_beams"),
        ({"active_radius": 40.0}, "active_radius"),
        ({"split": "dev"}, "split"),
    ],
)
def test_config_rejects_bad_values_naming_the_field(kwargs, field):
    with pytest.raises(ValueError, match=field):
        DrivingConfig(**kwargs)
    with pytest.raises(ValueError, match=field):
        DrivingConfig.from_dict(kwargs)


def test_config_from_dict_rejects_unknown_field_by_name():
    with pytest.raises(ValueError, match="nope"):
        DrivingConfig.from_dict({"nope": 1})


def test_config_round_trip_and_defaults():
    config = DrivingConfig(block_types=["straight", "curve"], split=None)
    assert config.block_types == ("straight", "curve")  # lists are normalised to tuples
    assert DrivingConfig.from_dict(config.to_dict()) == config
    assert DrivingConfig.from_dict(None) == DrivingConfig()
    assert DrivingConfig().lanes == 3 and DrivingConfig().split == "train"


def test_config_rejects_zero_simulation_frequency():
    with pytest.raises(ValueError, match="simulation_frequency"):
        DrivingConfig(simulation_frequency=0)


def test_config_rejects_fractional_lane_count():
    with pytest.raises(ValueError, match="lanes"):
        DrivingConfig(lanes=2.5)


# -- generation over the splits ----------------------------------------------------------------


def test_every_split_scene_generates_with_every_block_type(scenes):
    for split, seeds in (("train", TRAIN_SEEDS), ("test", TEST_SEEDS)):
        counts = Counter()
        for seed in seeds:
            scene = scenes[seed]
            assert scene.seed == seed
            assert 3 <= len(scene.blocks) <= 4  # min_blocks / max_blocks
            assert set(scene.blocks) <= set(BLOCK_TYPES)
            counts.update(scene.blocks)
        missing = set(BLOCK_TYPES) - set(counts)
        assert not missing, f"{split} split lacks block types {missing}: {dict(counts)}"
        assert sum(counts.values()) >= 3 * len(seeds)


def test_block_types_config_restricts_blocks():
    config = DrivingConfig(block_types=("straight", "curve"), min_blocks=2, max_blocks=2)
    for seed in range(10):
        scene = generate_scene(seed, config)
        assert len(scene.blocks) == 2
        assert set(scene.blocks) <= {"straight", "curve"}


# -- determinism -----------------------------------------------------------------------------


@pytest.mark.parametrize("seed", [0, 17, 1003, 1049])
def test_same_seed_gives_same_scene(seed):
    config = DrivingConfig()
    a, b = generate_scene(seed, config), generate_scene(seed, config)
    assert a.blocks == b.blocks
    assert a.route.segments == b.route.segments
    assert a.route.length == b.route.length
    geo_a, geo_b = _lane_geometry(a.network), _lane_geometry(b.network)
    assert geo_a.keys() == geo_b.keys()
    for key in geo_a:
        np.testing.assert_array_equal(geo_a[key], geo_b[key], err_msg=str(key))
    assert a.obstacles == b.obstacles
    assert a.vehicles == b.vehicles
    assert a.obstacle_events == b.obstacle_events
    assert [j.centre.tolist() for j in a.junctions] == [j.centre.tolist() for j in b.junctions]


def test_different_seeds_give_different_scenes(scenes):
    seeds = TRAIN_SEEDS[:20]
    pairs = list(itertools.combinations(seeds, 2))
    differ = sum(
        scenes[i].route.length != scenes[j].route.length or scenes[i].blocks != scenes[j].blocks for i, j in pairs
    )
    assert differ >= 0.95 * len(pairs)
    assert len({round(scenes[s].route.length, 6) for s in ALL_SEEDS}) >= 135


# -- geometry ------------------------------------------------------------------------------------


def test_route_geometry_is_connected_and_smooth(scenes):
    for seed, scene in scenes.items():
        route, net = scene.route, scene.network
        segs = route.segments
        assert segs[0][0] == "start"
        assert route.length > 150.0, seed
        for (a, b), (c, d) in zip(segs[:-1], segs[1:]):
            assert b == c, f"seed {seed}: segment {(a, b)} does not lead into {(c, d)}"
            ref1, ref2 = route.reference_lane((a, b)), route.reference_lane((c, d))
            gap = np.linalg.norm(ref1.position(ref1.length, 0) - ref2.position(0, 0))
            assert gap < 0.5, f"seed {seed}: reference lanes {(a, b)} -> {(c, d)} are {gap:.3f} m apart"
            dh = abs(utils.wrap_to_pi(ref1.heading_at(ref1.length) - ref2.heading_at(0)))
            assert dh < 1e-3, f"seed {seed}: heading jump {dh} at {(a, b)} -> {(c, d)}"
            # Every through lane continues into the lane with the same index.
            lanes1, lanes2 = net.graph[a][b], net.graph[c][d]
            for k in range(min(len(lanes1), len(lanes2))):
                gap_k = np.linalg.norm(lanes1[k].position(lanes1[k].length, 0) - lanes2[k].position(0, 0))
                assert gap_k < 0.5, f"seed {seed}: lane {k} breaks between {(a, b)} and {(c, d)}"
            assert len(lanes1) >= route.lanes and len(lanes2) >= route.lanes
        # Cumulative bookkeeping matches the lanes.
        lengths = [route.segment_length(seg) for seg in segs]
        assert route.length == pytest.approx(sum(lengths))
        assert route.segment_start(segs[-1]) == pytest.approx(sum(lengths[:-1]))


# -- obstacles and traffic -------------------------------------------------------------------------


def test_obstacles_lie_on_route_lanes_and_are_spread(scenes):
    n_events = 0
    for seed, scene in scenes.items():
        route, net = scene.route, scene.network
        for spec in scene.obstacles:
            assert route.segment_index(spec.lane_index) is not None, f"seed {seed}: obstacle off the route"
            assert 0 <= spec.lane_index[2] < route.lanes
            lane = net.get_lane(spec.lane_index)
            pos = lane.position(spec.longitudinal, spec.lateral)
            assert net.is_on_road(pos), f"seed {seed}: obstacle {spec} is off the road"
            assert _route_s(route, spec.lane_index, pos) > EGO_START + 25.0
        events = sorted(scene.obstacle_events, key=lambda e: e[2])
        n_events += len(events)
        for kind, lane_id, s in events:
            assert kind in ("broken_down", "cones")
            assert 0 <= lane_id < route.lanes
            assert 50.0 <= s <= route.length, f"seed {seed}: obstacle event at {s:.1f} m"
        for e1, e2 in zip(events[:-1], events[1:]):
            assert e2[2] - e1[2] >= 40.0, f"seed {seed}: obstacle events {e1} and {e2} closer than 40 m"
        # Each event's objects are there: a car + triangle, or four cones.
        kinds = Counter(spec.kind.__name__ for spec in scene.obstacles)
        n_broken = sum(e[0] == "broken_down" for e in events)
        n_cones = sum(e[0] == "cones" for e in events)
        assert kinds["BrokenDownCar"] == kinds["WarningTriangle"] == n_broken
        assert kinds["TrafficCone"] == 4 * n_cones
    assert n_events > 0


def test_traffic_starts_clear_of_the_ego(scenes):
    n_route_vehicles = 0
    for seed, scene in scenes.items():
        route, net = scene.route, scene.network
        ego_lane = net.get_lane((*route.segments[0], route.lanes // 2))
        ego_pos = ego_lane.position(EGO_START, 0)
        for spec in scene.vehicles:
            lane = net.get_lane(spec.lane_index)
            pos = lane.position(spec.longitudinal, 0)
            assert np.linalg.norm(pos - ego_pos) > 10.0, f"seed {seed}: {spec} starts at the ego"
            assert 0 <= spec.speed <= spec.target_speed
            if route.segment_index(spec.lane_index) is None:
                continue  # side traffic on a ramp, arm or the rest of a ring
            n_route_vehicles += 1
            s = _route_s(route, spec.lane_index, pos)
            assert not EGO_START <= s < EGO_START + 25.0, f"seed {seed}: vehicle {s - EGO_START:.1f} m ahead"
            assert s >= EGO_START + 25.0 - 1e-6  # and none behind it either
    assert n_route_vehicles > 100


def _spawn_overlaps(config: DrivingConfig, seeds) -> tuple[list, list]:
    """(vehicle-vehicle, vehicle-obstacle) overlaps right after reset, as (seed, kinds) lists."""
    env = make_gym_env(config)
    vv, vo = [], []
    try:
        for seed in seeds:
            env.reset(options={"scene_seed": seed})
            vehicles = list(env.road.vehicles)
            others = vehicles + list(env.road.objects)
            for i, a in enumerate(vehicles):
                for b in others[i + 1:]:
                    if np.linalg.norm(a.position - b.position) > 15.0:
                        continue
                    hit, _, _ = utils.are_polygons_intersecting(a.polygon(), b.polygon(), np.zeros(2), np.zeros(2))
                    if hit:
                        (vo if isinstance(b, Obstacle) else vv).append((seed, type(a).__name__, type(b).__name__))
    finally:
        env.close()
    return vv, vo


def test_nothing_overlaps_the_ego_at_spawn():
    env = make_gym_env(DrivingConfig())
    try:
        for seed in ALL_SEEDS[::5]:
            env.reset(options={"scene_seed": seed})
            ego = env.vehicle
            for other in [v for v in env.road.vehicles if v is not ego] + list(env.road.objects):
                assert np.linalg.norm(other.position - ego.position) > 8.0, seed
            assert not ego.crashed
    finally:
        env.close()


def test_traffic_does_not_spawn_on_obstacles():
    config = DrivingConfig(obstacle_density=3.0, traffic_density=3.0, truck_fraction=1.0)
    _, vehicle_on_obstacle = _spawn_overlaps(config, range(100))
    assert vehicle_on_obstacle == []


def test_traffic_vehicles_do_not_overlap_at_spawn():
    config = DrivingConfig(obstacle_density=0.0, traffic_density=3.0)
    vehicle_on_vehicle, _ = _spawn_overlaps(config, range(40))
    assert vehicle_on_vehicle == []


# -- density knobs ------------------------------------------------------------------------------------


def test_traffic_density_knob():
    seeds = TRAIN_SEEDS[:20]
    dense = np.mean([len(generate_scene(s, DrivingConfig(traffic_density=1.0)).vehicles) for s in seeds])
    sparse = np.mean([len(generate_scene(s, DrivingConfig(traffic_density=0.25)).vehicles) for s in seeds])
    none = [generate_scene(s, DrivingConfig(traffic_density=0.0, side_traffic_probability=0.0)) for s in seeds]
    assert dense > sparse > 0
    assert dense > 1.5 * sparse
    assert all(len(scene.vehicles) == 0 for scene in none)


def test_obstacle_density_knob():
    seeds = TRAIN_SEEDS[:20]
    zero = [generate_scene(s, DrivingConfig(obstacle_density=0.0)) for s in seeds]
    assert all(scene.obstacles == [] and scene.obstacle_events == [] for scene in zero)
    low = np.mean([len(generate_scene(s, DrivingConfig(obstacle_density=0.3)).obstacle_events) for s in seeds])
    high = np.mean([len(generate_scene(s, DrivingConfig(obstacle_density=2.0)).obstacle_events) for s in seeds])
    assert high > low > 0


def test_density_does_not_change_the_road():
    """Blocks are drawn before obstacles and traffic: the road of a seed is the same at any density."""
    for seed in (1, 1001):
        a = generate_scene(seed, DrivingConfig(traffic_density=0.1, obstacle_density=0.0))
        b = generate_scene(seed, DrivingConfig(traffic_density=2.0, obstacle_density=2.0))
        assert a.blocks == b.blocks
        assert a.route.segments == b.route.segments
        assert a.route.length == b.route.length
