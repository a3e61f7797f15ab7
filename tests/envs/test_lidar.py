"""Tests for the ego-framed lidar (pe_rlhf.envs.lidar)."""

from __future__ import annotations

import time

import numpy as np
import pytest

from pe_rlhf.envs.lidar import EgoLidar

BEAMS, RANGE = 240, 50.0


def _scan(lidar, ego_pos, ego_heading, boxes):
    """boxes: list of (cx, cy, heading, length, width)."""
    b = np.array(boxes, dtype=np.float64).reshape(-1, 5)
    return lidar.scan(np.asarray(ego_pos, float), ego_heading, b[:, :2], b[:, 2], b[:, 3], b[:, 4])


def _rot(v, a):
    c, s = np.cos(a), np.sin(a)
    return np.array([c * v[0] - s * v[1], s * v[0] + c * v[1]])


@pytest.fixture
def lidar():
    return EgoLidar(BEAMS, RANGE)


def test_box_straight_ahead(lidar):
    out = _scan(lidar, (0, 0), 0.0, [(20, 0, 0, 5, 2)])
    assert out[0] == pytest.approx((20 - 2.5) / RANGE, abs=1e-5)
    # The box (|y| <= 1 at x >= 17.5) subtends about +-3.3 deg: beams 0, +-1, +-2 only.
    assert np.all(out[[1, 2, -1, -2]] < 1.0)
    assert np.all(out[3:-2] == 1.0)
    assert np.all(out[BEAMS // 4 : 3 * BEAMS // 4 + 1] == 1.0)  # backwards half
    # Off-axis beam on the front face: distance 17.5 / cos(angle).
    a = 2 * np.pi / BEAMS
    assert out[1] == pytest.approx(17.5 / np.cos(a) / RANGE, abs=1e-5)


@pytest.mark.parametrize("angle", [0.3, np.pi / 2, 2.0, -2.7])
def test_frame_invariance(lidar, angle):
    ego = np.array([12.0, -7.0])
    boxes = [(20, 0, 0.0, 5, 2), (8, 6, 0.4, 4, 2), (-15, -3, 1.2, 10, 3), (3, -30, -0.5, 5, 2)]
    ref = _scan(lidar, ego, 0.0, [(ego[0] + x, ego[1] + y, h, L, W) for x, y, h, L, W in boxes])
    rotated = []
    for x, y, h, L, W in boxes:
        p = ego + _rot((x, y), angle)
        rotated.append((p[0], p[1], h + angle, L, W))
    out = _scan(lidar, ego, angle, rotated)
    assert (ref < 1).sum() > 10
    np.testing.assert_allclose(out, ref, atol=1e-5)


def test_box_to_the_side(lidar):
    out = _scan(lidar, (0, 0), 0.0, [(0, 10, 0, 5, 2)])
    assert out[BEAMS // 4] == pytest.approx((10 - 1) / RANGE, abs=1e-5)
    assert out[3 * BEAMS // 4] == 1.0
    # Same with the ego heading 90 deg: the box is now straight ahead.
    out = _scan(lidar, (0, 0), np.pi / 2, [(0, 10, 0, 5, 2)])
    assert out[0] == pytest.approx((10 - 1) / RANGE, abs=1e-5)


def test_occlusion(lidar):
    near = (10, 0, 0, 2, 2)  # face at x = 9, |y| <= 1
    far = (30, 0, np.pi / 2, 20, 2)  # face at x = 29, |y| <= 10
    out = _scan(lidar, (0, 0), 0.0, [far, near])
    assert out[0] == pytest.approx(9 / RANGE, abs=1e-5)
    assert out[1] == pytest.approx(9 / np.cos(2 * np.pi / BEAMS) / RANGE, abs=1e-5)
    # Beam 10 (15 deg): outside the near box's shadow (atan(1/9) ~ 6.3 deg), hits far face.
    a = 2 * np.pi * 10 / BEAMS
    assert 29 * np.tan(a) < 10
    assert out[10] == pytest.approx(29 / np.cos(a) / RANGE, abs=1e-5)
    assert out[-10] == pytest.approx(29 / np.cos(a) / RANGE, abs=1e-5)
    # The far box alone would be seen on beam 0 at 29 m.
    assert _scan(lidar, (0, 0), 0.0, [far])[0] == pytest.approx(29 / RANGE, abs=1e-5)


def _reference_scan(beams, max_range, ego, ego_heading, boxes):
    """Slow, independent reference: per-beam, per-box slab test in each box's frame."""
    out = np.ones(beams)
    for i in range(beams):
        ang = ego_heading + 2 * np.pi * i / beams
        d = np.array([np.cos(ang), np.sin(ang)])
        best = np.inf
        for cx, cy, h, length, width in boxes:
            o = _rot(np.asarray(ego, float) - (cx, cy), -h)  # ray origin, box frame
            u = _rot(d, -h)
            lo, hi = -np.inf, np.inf
            for k, half in ((0, length / 2), (1, width / 2)):
                if abs(u[k]) < 1e-15:
                    if abs(o[k]) > half:
                        lo, hi = np.inf, -np.inf
                    continue
                t1, t2 = sorted(((-half - o[k]) / u[k], (half - o[k]) / u[k]))
                lo, hi = max(lo, t1), min(hi, t2)
            if lo <= hi and hi >= 0:
                best = min(best, max(lo, 0.0))
        out[i] = min(best, max_range) / max_range
    return out


def test_matches_reference_on_random_scenes():
    rng = np.random.default_rng(42)
    lidar = EgoLidar(beams=72, max_range=30.0)
    n_hits = 0
    for _ in range(40):
        ego = rng.uniform(-50, 50, 2)
        heading = rng.uniform(-np.pi, np.pi)
        n = int(rng.integers(1, 12))
        boxes = [
            (*(ego + rng.uniform(-35, 35, 2)), rng.uniform(-np.pi, np.pi), rng.uniform(2, 12),
             rng.uniform(1, 3))
            for _ in range(n)
        ]
        ref = _reference_scan(72, 30.0, ego, heading, boxes)
        np.testing.assert_allclose(_scan(lidar, ego, heading, boxes), ref, atol=1e-5)
        n_hits += int((ref < 1).sum())
    assert n_hits > 100  # the scenes do exercise hits


def test_grazing_edge_through_ego_centre(lidar):
    # The box's lower face lies on the ray of beam 0: that beam hits the near corner.
    out = _scan(lidar, (0, 0), 0.0, [(20, 1, 0, 5, 2)])
    assert out[0] == pytest.approx(17.5 / RANGE, abs=1e-5)
    assert out[-1] == 1.0 and out[1] < 1.0


def test_out_of_range_and_partial(lidar):
    assert np.all(_scan(lidar, (0, 0), 0.0, [(60, 0, 0, 5, 2)]) == 1.0)
    # Centre beyond range but the face at 49.9 m is inside it.
    out = _scan(lidar, (0, 0), 0.0, [(52.4, 0, 0, 5, 2)])
    assert out[0] < 1.0
    assert out[0] == pytest.approx(49.9 / RANGE, abs=1e-5)


def test_output_format(lidar):
    rng = np.random.default_rng(0)
    n = 30
    out = lidar.scan(
        np.array([1.0, 2.0]), 0.7, rng.uniform(-60, 60, (n, 2)), rng.uniform(-np.pi, np.pi, n),
        rng.uniform(2, 10, n), rng.uniform(1, 3, n),
    )
    assert out.dtype == np.float32 and out.shape == (BEAMS,)
    assert np.all((out >= 0) & (out <= 1))
    small = EgoLidar(beams=7, max_range=5.0)
    assert small.scan(np.zeros(2), 0.0, np.zeros((0, 2)), [], [], []).shape == (7,)


def test_empty_is_all_ones(lidar):
    out = lidar.scan(np.zeros(2), 0.0, np.zeros((0, 2)), np.zeros(0), np.zeros(0), np.zeros(0))
    assert out.dtype == np.float32 and np.all(out == 1.0)


def test_ego_inside_object(lidar):
    out = _scan(lidar, (0, 0), 0.3, [(1.0, 0.5, 0.2, 5, 2), (20, 0, 0, 5, 2)])
    assert out[0] == 0.0
    assert np.all(out == 0.0)


def test_scan_objects_highway_env():
    from highway_env.road.road import Road, RoadNetwork
    from highway_env.vehicle.kinematics import Vehicle
    from highway_env.vehicle.objects import Obstacle

    road = Road(network=RoadNetwork.straight_road_network(3), np_random=np.random.default_rng(0))
    ego = Vehicle(road, [0.0, 4.0], heading=0.0, speed=20.0)
    obstacle = Obstacle(road, [30.0, 4.0])
    road.vehicles.append(ego)
    road.objects.append(obstacle)
    lidar = EgoLidar(BEAMS, RANGE)
    out = lidar.scan_objects(ego, road.vehicles + road.objects)
    # The ego (which contains its own centre) is excluded, otherwise everything would read 0.
    assert out[0] == pytest.approx((30 - obstacle.LENGTH / 2) / RANGE, abs=1e-5)
    assert np.all(out[BEAMS // 4 : 3 * BEAMS // 4 + 1] == 1.0)
    np.testing.assert_array_equal(out, lidar.scan_objects(ego, [obstacle]))
    assert np.all(lidar.scan_objects(ego, [ego]) == 1.0)


@pytest.mark.parametrize(
    "kwargs, name",
    [({"beams": 0}, "beams"), ({"beams": 2.5}, "beams"), ({"max_range": 0.0}, "max_range"),
     ({"max_range": -3.0}, "max_range")],
)
def test_invalid_constructor_args(kwargs, name):
    with pytest.raises(ValueError, match=name):
        EgoLidar(**kwargs)


def test_mismatched_arrays(lidar):
    with pytest.raises(ValueError, match="same length"):
        lidar.scan(np.zeros(2), 0.0, np.ones((3, 2)), np.zeros(2), np.ones(3), np.ones(3))
    with pytest.raises(ValueError, match="same length"):
        lidar.scan(np.zeros(2), 0.0, np.ones((3, 2)), np.zeros(3), np.ones(3), np.ones(4))
    with pytest.raises(ValueError, match="ego_position"):
        lidar.scan(np.zeros(3), 0.0, np.ones((3, 2)), np.zeros(3), np.ones(3), np.ones(3))


@pytest.mark.timing
def test_performance(lidar):
    rng = np.random.default_rng(1)
    n = 20
    ang, r = rng.uniform(-np.pi, np.pi, n), rng.uniform(8, 45, n)  # none contains the ego
    centres = np.stack([r * np.cos(ang), r * np.sin(ang)], axis=1)
    args = (np.zeros(2), 0.3, centres, rng.uniform(-np.pi, np.pi, n), np.full(n, 5.0),
            np.full(n, 2.0))
    assert 0.0 < lidar.scan(*args).min() < 1.0
    t0 = time.perf_counter()
    for _ in range(200):
        lidar.scan(*args)
    assert (time.perf_counter() - t0) / 200 < 1e-3
