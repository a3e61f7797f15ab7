"""``DrivingEnv``: procedural highway-env scenes driven by a continuous ``[steering, throttle]``.

Reward (baselines and evaluation only) and cost follow the spec (MetaDrive's scheme):
``reward = (d_t - d_{t-1}) + 0.1 * v_t / v_max``, replaced on the last step by the
terminal term: +20 at the destination, -5 for a crash or leaving the road.
``cost = 1`` on a step in collision with a vehicle, an obstacle, or off the road.
Episodes end on success, crash or out of road (terminated) or at ``horizon`` steps
(truncated). ``info`` holds, every step: ``cost``, ``success``, ``crash_vehicle``,
``crash_object``, ``out_of_road``, ``route_completion``, ``travel_distance`` [m, odometer],
``velocity`` [km/h], ``overtakes`` (vehicles passed, once each), ``scene_seed``, ``sim_error``.

Simulator faults: if a step raises, or returns a non-finite observation, reward or info value, the
episode ends there as truncated with ``info["sim_error"] = True`` (observation and info of the last
good step, reward and cost 0) and a warning on the ``pe_rlhf.envs`` logger naming the scene, the
step and the fault; the next ``reset`` loads a fresh scene, so a run goes on. A ``reset`` whose first observation or
info is non-finite draws another scene (logged, counted in ``sim_errors``); with a given ``scene_seed``, or
``MAX_CONSECUTIVE_SIM_ERRORS`` scenes in a row, it raises :class:`SimulatorError`: nothing non-finite leaves the env.
``MAX_CONSECUTIVE_SIM_ERRORS`` faults in a row (no good step between them) re-raise: the simulator
is broken, not unlucky.

Resuming mid-episode: :meth:`DrivingEnv.resume_state` is plain JSON data (the scene-drawing RNG, the
scene in progress and the actions executed in it, the fault counters); :meth:`DrivingEnv.load_resume_state`
reloads that scene and replays the actions, which reproduces the road exactly (a scene's traffic has
its own RNG, seeded by the scene), so a checkpointed run continues its episode where it was.
"""

from __future__ import annotations

import logging
from collections import OrderedDict

import gymnasium as gym
import numpy as np
from highway_env.envs.common.abstract import AbstractEnv
from highway_env.envs.common.graphics import EnvViewer
from highway_env.vehicle.kinematics import Vehicle
from highway_env.vehicle.objects import Obstacle

from pe_rlhf.envs.action import action_to_controls
from pe_rlhf.envs.config import DrivingConfig
from pe_rlhf.envs.fast_road import ActiveRoad
from pe_rlhf.envs.lidar import EgoLidar
from pe_rlhf.envs.observation import V_MAX, build_observation, observation_size
from pe_rlhf.envs.scene import EGO_SPEED, EGO_START, Scene, generate_scene
from pe_rlhf.envs.splits import scene_seeds
from pe_rlhf.envs.traffic import release_claims

# Overlapping lanes (ring entries, ramps) make highway-env warn about routes every substep.
logging.getLogger("highway_env.road.road").setLevel(logging.ERROR)

SUCCESS_REWARD = 20.0
CRASH_PENALTY = 5.0
OUT_OF_ROAD_PENALTY = 5.0
ROAD_EDGE_MARGIN = 1.0  # [m] the ego centre may pass the edge line by this much before it is off road
SCENE_CACHE = 128
MAX_CONSECUTIVE_SIM_ERRORS = 5
log = logging.getLogger("pe_rlhf.envs")


class SimulatorError(RuntimeError):
    """The simulator failed on ``MAX_CONSECUTIVE_SIM_ERRORS`` steps in a row."""


class EgoVehicle(Vehicle):
    """The controlled car: a kinematic bicycle that brakes to a stop and never reverses."""

    LENGTH = 4.5
    WIDTH = 1.9
    MAX_SPEED = 30.0

    def set_controls(self, steering_angle: float, acceleration: float) -> None:
        self.action = {"steering": steering_angle, "acceleration": acceleration}

    def act(self, action=None) -> None:
        pass  # controls are set once per env step by ``set_controls``

    def step(self, dt: float) -> None:
        if self.speed <= 0.0 and self.action["acceleration"] < 0.0:
            self.action["acceleration"] = 0.0
        super().step(dt)
        self.speed = float(np.clip(self.speed, 0.0, self.MAX_SPEED))


class DrivingEnv(AbstractEnv):
    """A gymnasium env on highway-env; see the module docstring for reward, cost and info.

    ``reset(options={"scene_seed": k})`` loads scene ``k``; without it a seed is drawn
    from the configured split (``train``/``test``) with the env's RNG, or any
    integer when ``split`` is None. Observation layout: :mod:`pe_rlhf.envs.observation`.
    """

    metadata = {"render_modes": ["human", "rgb_array"], "render_fps": 10}

    def __init__(self, config: DrivingConfig | dict | None = None, render_mode: str | None = None):
        self.world = config if isinstance(config, DrivingConfig) else DrivingConfig.from_dict(config)
        self.lidar = EgoLidar(self.world.lidar_beams, self.world.lidar_range)
        self._scenes: OrderedDict[int, Scene] = OrderedDict()
        self.last_action = np.zeros(2, dtype=np.float32)
        self.sim_errors = 0  # steps ended by a simulator fault, over the env's life
        self._consecutive_errors = 0
        self._last_good: tuple[np.ndarray, dict] | None = None
        self._episode_actions: list[np.ndarray] = []  # executed since the last reset (resume_state)
        super().__init__(
            {
                "simulation_frequency": self.world.simulation_frequency,
                "policy_frequency": self.world.policy_frequency,
                "screen_width": 800,
                "screen_height": 450,
                "scaling": 4.0,
                "centering_position": [0.35, 0.5],
            },
            render_mode,
        )

    # -- spaces ---------------------------------------------------------------------------
    def define_spaces(self) -> None:
        n = observation_size(self.world.lidar_beams, self.world.lane_features)
        self.observation_space = gym.spaces.Box(-1.0, 1.0, (n,), dtype=np.float32)
        self.action_space = gym.spaces.Box(-1.0, 1.0, (2,), dtype=np.float32)
        self.action_type = None
        self.observation_type = None

    # -- scenes ---------------------------------------------------------------------------
    def scene(self, seed: int) -> Scene:
        """The (cached) blueprint of scene ``seed``."""
        seed = int(seed)
        if seed not in self._scenes:
            self._scenes[seed] = generate_scene(seed, self.world)
            if len(self._scenes) > SCENE_CACHE:
                self._scenes.popitem(last=False)
        return self._scenes[seed]

    def _draw_scene_seed(self) -> int:
        if self.world.split is None:
            return int(self.np_random.integers(0, 2**31 - 1))
        seeds = scene_seeds(self.world.split)
        return int(seeds[self.np_random.integers(0, len(seeds))])

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        gym.Env.reset(self, seed=seed)
        options = options or {}
        unknown = set(options) - {"scene_seed"}
        if unknown:
            raise ValueError(f"unknown reset option(s) {sorted(unknown)}; allowed: ['scene_seed']")
        scene_seed = options.get("scene_seed")
        for attempt in range(1, MAX_CONSECUTIVE_SIM_ERRORS + 1):  # a non-finite start: another scene, or stop
            self.scene_seed = self._draw_scene_seed() if scene_seed is None else int(scene_seed)
            self.time = self.steps = 0
            self.done = False
            self._episode_actions = []
            self._load(self.scene(self.scene_seed))
            obs = build_observation(self)
            info = self._info_dict(cost=0.0)
            fault = _non_finite((obs, 0.0, False, False, info))
            if fault is None:
                break
            self.sim_errors += 1
            if scene_seed is not None or attempt == MAX_CONSECUTIVE_SIM_ERRORS:
                raise SimulatorError(f"scene {self.scene_seed}: the simulator's first observation is not finite "
                                     f"({fault})" + ("" if scene_seed is not None else f", {attempt} scenes in a row"))
            log.warning("scene %s reset: simulator fault (%s); drawing another scene", self.scene_seed, fault[:300])
        self._last_good = (obs, info)
        if self.render_mode == "human":
            self.render()
        return obs, info

    def _reset(self) -> None:  # AbstractEnv hook; our reset() does the work
        pass

    def _load(self, scene: Scene) -> None:
        self.current_scene = scene
        self.route = scene.route
        road = ActiveRoad(
            network=scene.network,
            np_random=np.random.RandomState(scene.seed % 2**32),
            record_history=False,
            neighbour_vehicles_connected_lanes=True,
            active_radius=self.world.active_radius,
        )
        start = (*scene.route.segments[0], self.world.lanes // 2)
        lane = scene.network.get_lane(start)
        ego = EgoVehicle(road, lane.position(EGO_START, 0), lane.heading_at(EGO_START), EGO_SPEED)
        road.vehicles.append(ego)
        road.focus = ego
        scene.populate(road)
        self.road, self.vehicle = road, ego
        self.route_segment, self.progress = scene.route.project(ego.position, 0)
        self.travel_distance = 0.0
        self.last_action = np.zeros(2, dtype=np.float32)
        self._overtaken: set[int] = set()
        self._ahead: dict[int, bool] = {}
        self.crash_vehicle = self.crash_object = self.out_of_road = self.success = False

    # -- dynamics ------------------------------------------------------------------------
    def step(self, action):
        """One policy step (see the module docstring); a simulator fault ends the episode as truncated."""
        if self.road is None or self.vehicle is None or self._last_good is None:
            raise RuntimeError("call reset() before step()")
        if not np.isfinite(np.asarray(action, dtype=np.float64)).all():
            raise ValueError(f"action {np.asarray(action).tolist()} is not finite (a caller's bug, not a simulator "
                             "fault: pe_rlhf's InterventionTransform never executes one)")
        step = round(self.time * self.world.policy_frequency)  # this step's index in the episode
        self._episode_actions.append(np.array(action, copy=True))
        try:
            out = self._simulate(action)
            fault, error = _non_finite(out), None
        except Exception as e:  # noqa: BLE001 - any simulator failure ends only this episode
            fault, error = f"{type(e).__name__}: {e}", e
        if fault is None:
            self._consecutive_errors = 0
            self._last_good = (out[0], out[4])
            return out
        return self._fault_step(step, fault, error)

    def resume_state(self) -> dict:
        """What :meth:`load_resume_state` needs to continue from here, as JSON data: ``np_random`` (the
        scene draws' bit-generator state), ``scene_seed`` (None before the first reset), ``actions`` (each
        executed since that reset, as lists, with their ``dtype``) and the fault counters."""
        actions = self._episode_actions
        return {"np_random": self.np_random.bit_generator.state, "scene_seed": getattr(self, "scene_seed", None),
                "dtype": str(actions[0].dtype) if actions else "float32", "actions": [a.tolist() for a in actions],
                "sim_errors": int(self.sim_errors), "consecutive_errors": int(self._consecutive_errors)}

    def load_resume_state(self, state: dict) -> None:
        """Continue from :meth:`resume_state`: reload its scene and replay its actions (rendering off), then
        set the scene RNG and the fault counters as they were."""
        if state["scene_seed"] is not None:
            render_mode, self.render_mode = self.render_mode, None
            try:
                self.reset(options={"scene_seed": int(state["scene_seed"])})
                for action in state["actions"]:
                    self.step(np.asarray(action, dtype=state["dtype"]))
            finally:
                self.render_mode = render_mode
        self.np_random.bit_generator.state = state["np_random"]
        self.sim_errors, self._consecutive_errors = int(state["sim_errors"]), int(state["consecutive_errors"])

    def _fault_step(self, step: int, fault: str, error: Exception | None):
        """End the episode after a simulator fault: the last good observation and info, truncated."""
        self.sim_errors += 1
        self._consecutive_errors += 1
        if self._consecutive_errors >= MAX_CONSECUTIVE_SIM_ERRORS:
            raise SimulatorError(f"the simulator failed on {MAX_CONSECUTIVE_SIM_ERRORS} steps in a row "
                                 f"(scene {self.scene_seed}): {fault}") from error
        log.warning("scene %s step %d: simulator fault (%s); episode ended as truncated (sim_error)",
                    self.scene_seed, step, fault[:300])
        obs, info = self._last_good
        return obs.copy(), 0.0, False, True, {**info, "cost": 0.0, "sim_error": True}

    def _simulate(self, action):
        steering, accel = action_to_controls(action)
        self.last_action = np.clip(np.asarray(action, dtype=np.float32).reshape(2), -1, 1)
        ego = self.vehicle
        ego.set_controls(steering, accel)
        frames = self.world.simulation_frequency // self.world.policy_frequency
        dt = 1.0 / self.world.simulation_frequency
        for _ in range(frames):
            self.road.act()
            self.road.step(dt)
            self.travel_distance += ego.speed * dt
            self.steps += 1
            self._automatic_rendering()
        self.time += 1.0 / self.world.policy_frequency
        self._remove_finished_vehicles()
        previous = self.progress
        self.route_segment, self.progress = self.route.project(ego.position, self.route_segment)
        self._update_events()
        self._update_overtakes()
        terminated = self.success or self.crash_vehicle or self.crash_object or self.out_of_road
        truncated = not terminated and self.time * self.world.policy_frequency >= self.world.horizon - 1e-6
        if self.success:
            reward = SUCCESS_REWARD
        elif self.crash_vehicle or self.crash_object:
            reward = -CRASH_PENALTY
        elif self.out_of_road:
            reward = -OUT_OF_ROAD_PENALTY
        else:
            reward = (self.progress - previous) + 0.1 * ego.speed / V_MAX
        cost = float(self.crash_vehicle or self.crash_object or self.out_of_road)
        obs = build_observation(self)
        info = self._info_dict(cost)
        if self.render_mode == "human":
            self.render()
        return obs, float(reward), bool(terminated), bool(truncated), info

    def _update_events(self) -> None:
        ego = self.vehicle
        if ego.crashed and not (self.crash_vehicle or self.crash_object):
            if isinstance(self.road.focus_hit, Obstacle):
                self.crash_object = True
            else:
                self.crash_vehicle = True
        if not self.road.network.is_on_road(ego.position, ROAD_EDGE_MARGIN):
            self.out_of_road = True
        on_route = self.route.segment_index(ego.lane_index) is not None
        if on_route and self.progress >= self.route.length - 5.0 and not self.out_of_road:
            self.success = not (self.crash_vehicle or self.crash_object)

    def _update_overtakes(self) -> None:
        """Count vehicles that were ahead of the ego on the route and are now behind it."""
        ego = self.vehicle
        for v in self.road.vehicles:
            if v is ego or np.linalg.norm(v.position - ego.position) > 60.0:
                continue
            k = self.route.segment_index(v.lane_index)
            if k is None:
                continue
            _, s = self.route.project(v.position, k)
            ahead = s > self.progress
            if self._ahead.get(id(v)) and not ahead:
                self._overtaken.add(id(v))
            self._ahead[id(v)] = ahead

    def _remove_finished_vehicles(self) -> None:
        graph = self.road.network.graph
        keep = []
        for v in self.road.vehicles:
            if v is not self.vehicle and v.lane_index[1] not in graph and v.lane.after_end(v.position):
                release_claims(v)
                continue
            keep.append(v)
        self.road.vehicles = keep

    def _info_dict(self, cost: float) -> dict:
        return {
            "cost": float(cost),
            "success": bool(self.success),
            "crash_vehicle": bool(self.crash_vehicle),
            "crash_object": bool(self.crash_object),
            "out_of_road": bool(self.out_of_road),
            "route_completion": float(self.progress / self.route.length),
            "travel_distance": float(self.travel_distance),
            "velocity": float(self.vehicle.speed * 3.6),
            "overtakes": int(len(self._overtaken)),
            "scene_seed": int(self.scene_seed),
            "sim_error": False,
        }

    # -- rendering -----------------------------------------------------------------------
    def render(self):
        if self.render_mode is None:
            gym.logger.warn("render() needs render_mode='rgb_array' or 'human'")
            return None
        if self.viewer is None:
            self.viewer = EnvViewer(self)
            self.viewer.enabled = True  # highway-env disables drawing under SDL's dummy driver
        self.enable_auto_render = self.render_mode == "human"
        self.viewer.display()
        if not self.viewer.offscreen:
            self.viewer.handle_events()
        if self.render_mode == "rgb_array":
            return self.viewer.get_image()
        return None


def _non_finite(step: tuple) -> str | None:
    """What is not finite in a step's ``(obs, reward, terminated, truncated, info)``, or None."""
    obs, reward, _, _, info = step
    if not np.isfinite(obs).all():
        return f"observation has {int((~np.isfinite(obs)).sum())} non-finite values"
    if not np.isfinite(reward):
        return f"reward is {reward}"
    bad = [k for k, v in info.items() if isinstance(v, float) and not np.isfinite(v)]
    return f"info {bad} not finite" if bad else None
