"""The floor where it is decided: executed actions of the hybrid (IDM-MOBIL drives, the mentor takes over,
the selector picks), against the mentor's takeovers executed as they come and IDM-MOBIL alone.

    python benchmarks/ensemble_selection.py --mentors professional adversarial --split train --scenes 0-19 \\
        --value expert --epsilons 0.5 1.5 --switch-margins none 1.0 --json out.json

The agent is the physics policy (``idm-mobil``, braking for obstacles); every takeover runs through the same
:class:`~pe_rlhf.transforms.InterventionTransform` and :class:`~pe_rlhf.transforms.HybridActionSelector` as
training (no copy of their logic). Rows per mentor:

- ``idm-mobil``: no mentor (the floor the hybrid must keep);
- ``as-is``: the mentor's takeovers executed as they come (HACO's executed actions);
- ``hybrid eps=E margin=M``: PE-RLHF's executed actions with ``selector.value`` (``--value``).

``--warmup``: instead, the warm-up's executed actions: the mentor drives every step (``warmup``, the paper's
warm-up) or drives under the selector's judgement (``warmup+selection eps=E``: ``selector.warmup_selection``).

Each row: success, safety violation (episodes with a crash or leaving the road), timeouts, takeover share of
steps and the share of takeover steps executing the mentor. Calibrate on ``--split train``; the test split is
for the final check. Importable: :func:`drive` and :func:`measure` run nothing at import.
"""
from __future__ import annotations

import argparse
import json
import math
import time
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from pe_rlhf.envs import DrivingConfig, scene_seeds
from pe_rlhf.envs.splits import SPLITS
from pe_rlhf.envs.torchrl_env import make_env, unwrap
from pe_rlhf.evaluation.policies import PhysicsPolicyAdapter, make_policy, register_policy
from pe_rlhf.mentors import make_mentor
from pe_rlhf.physics import IDMMobilPolicy, PhysicsConfig, SafetyForecastConfig, SafetyForecastValue
from pe_rlhf.physics.road_users import MODELS as ROAD_USER_MODELS
from pe_rlhf.physics.safety import RECOVERIES
from pe_rlhf.algorithms.proxy_q.value_expert import load_value_expert, parse_value_source
from pe_rlhf.transforms import HybridActionSelector, InterventionTransform


class RegisteredAgent:
    """An evaluation policy by name (``pe_rlhf.evaluation.make_policy``: ``idm-mobil``, ``random``, ...) as a
    TorchRL policy on ``env``: reads ``observation``, writes ``action``."""

    def __init__(self, env, name: str = "idm-mobil", seed: int = 0):
        self.sim, self.policy = unwrap(env), make_policy(name, seed)

    def __call__(self, td):
        obs = td.get("observation").numpy()
        td.set("action", torch.as_tensor(np.asarray(self.policy(obs, self.sim), np.float32)))
        return td


class CrawlingDriver:
    """IDM-MOBIL (seeing obstacles) steering with a throttle that holds ``speed`` m/s: a car that drives safely and
    makes little progress (the learned agents' crawl), for the takeover-rate table (``crawl-4`` holds 4 m/s)."""

    def __init__(self, speed: float):
        self.speed, self.physics = float(speed), PhysicsPolicyAdapter(PhysicsConfig(see_obstacles=True))

    def reset(self) -> None:
        self.physics.reset()

    def __call__(self, obs, env) -> np.ndarray:
        action = self.physics(obs, env)
        action[1] = min(float(action[1]), float(np.clip(0.5 * (self.speed - env.vehicle.speed), -1.0, 1.0)))
        return action


for _speed in (2, 4, 6):
    register_policy(f"crawl-{_speed}", lambda seed, v=_speed: CrawlingDriver(v), overwrite=True)


def drive(mentor: str | None, scenes: list[int], split: str = "train", selector: HybridActionSelector | None = None,
          mentor_seed: int = 0, world: DrivingConfig | None = None, progress: str | None = None,
          driver: str = "idm-mobil", mentor_kwargs: dict | None = None, warmup: bool = False) -> dict:
    """Episodes of ``driver`` (an evaluation policy name; IDM-MOBIL by default) under ``mentor`` (None: alone),
    the selector picking when given; a dict of rates. ``warmup``: the mentor drives every step, as in a
    run's warm-up (judged by the selector when given: ``warmup_selection``)."""
    world = world or DrivingConfig(split=split, lane_features=True)
    env = make_env(world)
    transform = None
    if mentor is not None:
        physics = IDMMobilPolicy(PhysicsConfig()) if selector is not None else None
        transform = InterventionTransform(make_mentor(mentor, mentor_seed, **(mentor_kwargs or {})), selector, physics,
                                          warmup_steps=10**12 if warmup else 0,
                                          warmup_selection=warmup and selector is not None)
        env.append_transform(transform)
    agent = RegisteredAgent(env, driver)
    rows = []
    for seed in tqdm(scenes, desc=progress, leave=False, disable=progress is None):
        agent.policy.reset()
        td = env.reset(scene_seed=int(seed))
        steps = takeover = chosen = starts = switches = 0
        previous = None  # the last takeover step's choice (mentor?), None outside a takeover
        while True:
            td = agent(td)
            td = env.step(td)
            nxt = td.get("next")
            steps += 1
            if transform is not None:
                taken, mentor_chosen = bool(nxt.get("intervention")), bool(nxt.get("mentor_selected"))
                takeover += taken
                chosen += mentor_chosen
                starts += bool(nxt.get("intervention_start"))
                switches += taken and previous is not None and mentor_chosen != previous
                previous = mentor_chosen if taken else None
            if bool(nxt.get("done")):
                break
            td = nxt.exclude("reward", "done", "terminated", "truncated")
        failed = bool(nxt.get("crash_vehicle") | nxt.get("crash_object") | nxt.get("out_of_road"))
        rows.append({"scene": int(seed), "success": bool(nxt.get("success")), "violation": failed,
                     "timeout": not failed and not bool(nxt.get("success")), "steps": steps,
                     "takeover_steps": takeover, "mentor_steps": chosen, "takeovers": starts,
                     "switches": switches})
    env.close()
    total_takeover = sum(r["takeover_steps"] for r in rows)
    return {"episodes": len(rows),
            "success": float(np.mean([r["success"] for r in rows])),
            "violation": float(np.mean([r["violation"] for r in rows])),
            "timeout": float(np.mean([r["timeout"] for r in rows])),
            "takeover_share": total_takeover / max(sum(r["steps"] for r in rows), 1),
            "mentor_share": sum(r["mentor_steps"] for r in rows) / max(total_takeover, 1),
            "switches_per_takeover": sum(r["switches"] for r in rows) / max(sum(r["takeovers"] for r in rows), 1),
            "per_episode": rows}


def forecast_value(hold: float = 1.0, recovery: str | None = None, one_lane: bool = False,
                   road_users: str | None = None, horizon: float | None = None) -> SafetyForecastValue:
    """The forecast value source held ``hold`` seconds, with ``recovery``, ``road_users`` and ``horizon`` (None: the
    config's defaults, as ``selector.value=forecast`` builds it)."""
    options = {k: v for k, v in (("recovery", recovery), ("road_users", road_users), ("horizon", horizon))
               if v is not None}
    return SafetyForecastValue(SafetyForecastConfig(hold=hold, hold_one_lane=one_lane, **options))


def measure(mentors: list[str], scenes: list[int], split: str, value: str, epsilons: list[float],
            switch_margins: list[float | None], variance_threshold: float | None = None,
            forecast_hold: float = 1.0, forecast_recovery: str | None = None, veto_patience: int = 1,
            imminent_failure: float | None = None, one_lane: bool = False,
            persistence: list[str] = ("off",), references: list[str] = ("physics",),
            strict: list[bool] = (False,), progress_margins: list[float | None] = (None,), save=None,
            floor: bool = True, road_users: str | None = None, done: list[dict] = (),
            latch_release_speeds: list[float | None] = (None,), forecast_horizon: float | None = None) -> list[dict]:
    """Every row (see the module docstring) for every mentor, IDM-MOBIL alone once (``floor=False``: not, it is
    measured apart). ``save(results)`` is called after each row (a long run keeps what it measured); rows of
    ``done`` (a saved run's, matched by mentor and label) are kept, not measured again."""
    world = DrivingConfig(split=split, lane_features=True)
    kind, path = parse_value_source(value)
    if kind == "warmup":
        raise SystemExit("--value: a warm-up ensemble exists only inside a run; use expert, expert:PATH or "
                         "forecast")
    ensemble = forecast_value(forecast_hold, forecast_recovery, one_lane, road_users, forecast_horizon) \
        if kind == "forecast" \
        else load_value_expert(path, world_obs_dim(world))
    results = _Rows(save)
    kept = {(r["mentor"], r["row"]): r for r in done if [e["scene"] for e in r.get("per_episode", [])] == scenes}

    def add(mentor: str | None, label: str, settings: dict, run) -> None:
        results.append(kept.get((mentor, label)) or {"mentor": mentor, "row": label, **settings, **run()})

    if floor:
        add(None, "idm-mobil", {}, lambda: drive(None, scenes, split, world=world, progress="idm-mobil"))
    for mentor in mentors:
        add(mentor, "as-is", {}, lambda: drive(mentor, scenes, split, world=world, progress=f"{mentor} as-is"))
        for eps in epsilons:
            for margin in switch_margins:
                for persist, reference, st, pm, release in [
                        (p, r, t, m, v) for p in persistence for r in references for t in strict
                        for m in progress_margins for v in latch_release_speeds]:
                    selector = HybridActionSelector(ensemble, eps, variance_threshold, switch_margin=margin,
                                                    veto_patience=veto_patience, imminent_failure=imminent_failure,
                                                    persistence=persist, reference=reference, strict_in_danger=st,
                                                    progress_margin=pm, latch_release_speed=release)
                    label = f"hybrid eps={eps:g} margin={'none' if margin is None else f'{margin:g}'}"
                    if veto_patience > 1:
                        label += f" patience={veto_patience} imminent={imminent_failure}"
                    if persist != "off":
                        label += f" persistence={persist}"
                    if reference != "physics":
                        label += f" reference={reference}"
                    if st:
                        label += " strict"
                    if pm is not None:
                        label += f" progress={pm:g}"
                    if release is not None:
                        label += f" release={release:g}"
                    if forecast_horizon is not None:
                        label += f" horizon={forecast_horizon:g}"
                    add(mentor, label, {"epsilon_select": eps, "switch_margin": margin, "persistence": persist,
                                        "reference": reference, "strict_in_danger": st, "progress_margin": pm,
                                        "latch_release_speed": release},
                        lambda: drive(mentor, scenes, split, selector, world=world, progress=f"{mentor} {label}"))
    return list(results)


class _Rows(list):
    """The rows measured so far; each append prints the row and hands the list to ``save`` (when given)."""

    def __init__(self, save=None):
        super().__init__()
        self.save = save

    def append(self, row: dict) -> None:
        super().append(row)
        print(f"{row['mentor'] or '-'} | {row['row']}: success {row['success']:.2f}, violation "
              f"{row['violation']:.2f}, mentor share {row['mentor_share']:.2f}", flush=True)
        if self.save is not None:
            self.save(list(self))


def warmup_rows(mentors: list[str], scenes: list[int], split: str, value: str, epsilons: list[float]) -> list[dict]:
    """The warm-up's executed actions per mentor: the mentor alone, then judged by ``value`` at each epsilon."""
    world = DrivingConfig(split=split, lane_features=True)
    kind, path = parse_value_source(value)
    if kind == "warmup":
        raise SystemExit("--warmup judges the warm-up: a value fitted on it cannot; use forecast or expert")
    ensemble = forecast_value() if kind == "forecast" else load_value_expert(path, world_obs_dim(world))
    results = []
    for mentor in mentors:
        results.append({"mentor": mentor, "row": "warmup", **drive(mentor, scenes, split, world=world, warmup=True,
                                                                   progress=f"{mentor} warm-up")})
        for eps in epsilons:
            label = f"warmup+selection eps={eps:g}"
            results.append({"mentor": mentor, "row": label, "epsilon_select": eps,
                            **drive(mentor, scenes, split, HybridActionSelector(ensemble, eps), world=world,
                                    warmup=True, progress=f"{mentor} {label}")})
    return results


def takeover_rates(mentors: list[str], drivers: list[str], scenes: list[int], split: str = "train",
                   mentor_kwargs: dict | None = None) -> list[dict]:
    """Each mentor's takeover share of steps watching each driver, its takeovers executed as they come (HACO):
    a competent driver should rarely be taken over, a bad one nearly always (``crawl-<v>``: a safe driver holding
    v m/s, which a person would take over for making no progress)."""
    world = DrivingConfig(split=split, lane_features=True)
    label = "".join(f" {k}={v}" for k, v in (mentor_kwargs or {}).items())
    return [{"mentor": m + label, "row": f"driver={d}", "driver": d,
             **drive(m, scenes, split, world=world, progress=f"{m} watching {d}", driver=d,
                     mentor_kwargs=mentor_kwargs)}
            for m in mentors for d in drivers]


def world_obs_dim(world: DrivingConfig) -> int:
    from pe_rlhf.envs.observation import observation_size

    return observation_size(world.lidar_beams, world.lane_features)


def parse_scenes(text: str, split: str) -> list[int]:
    lo, _, hi = text.partition("-")
    seeds = scene_seeds(split)
    first, last = int(lo), int(hi or lo)
    return [s for s in seeds if first <= s <= last] or list(seeds[first:last + 1])


def mentor_kwargs(items: list[str], stall_speed: float | None, parser) -> dict | None:
    """``FIELD=VALUE`` items (numbers, or true/false) and ``--stall-speed`` as the mentors' SkillProfile kwargs."""
    out = {} if stall_speed is None else {"stall_speed": stall_speed}
    for item in items:
        field, sep, value = item.partition("=")
        if not sep or not field:
            parser.error(f"--mentor-kwargs {item!r}: FIELD=VALUE")
        try:
            out[field] = {"true": True, "false": False}[value.lower()] if value.lower() in ("true", "false") \
                else (int(value) if value.lstrip("-").isdigit() else float(value))
        except ValueError:
            parser.error(f"--mentor-kwargs {item!r}: VALUE must be a number, true or false")
    return out or None


def margin_arg(text: str) -> float | None:
    return None if text.lower() == "none" else (math.inf if text.lower() == "inf" else float(text))


def format_table(results: list[dict]) -> str:
    lines = ["| mentor | row | success | violation | timeout | takeover share | mentor share | switches a takeover |",
             "|---|---|---|---|---|---|---|---|"]
    for r in results:
        lines.append(f"| {r['mentor'] or '-'} | {r['row']} | {r['success']:.2f} | {r['violation']:.2f} | "
                     f"{r['timeout']:.2f} | {r['takeover_share']:.2f} | {r['mentor_share']:.2f} | "
                     f"{r['switches_per_takeover']:.2f} |")
    return "\n".join(lines)


def main(argv=None) -> list[dict]:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--mentors", nargs="+", default=["professional", "adversarial"])
    parser.add_argument("--split", choices=list(SPLITS), default="train")
    parser.add_argument("--scenes", default="0-19",
                        help="a range of the split's scene seeds (train 0-..., validation 500-..., test 1000-...)")
    parser.add_argument("--value", default="expert", help="selector.value: expert | expert:PATH | forecast")
    parser.add_argument("--epsilons", type=float, nargs="+", default=[0.5, 1.5])
    parser.add_argument("--switch-margins", type=margin_arg, nargs="+", default=[None], help="none, a number, or inf")
    parser.add_argument("--variance-threshold", type=float, default=None)
    parser.add_argument("--forecast-hold", type=float, default=1.0,
                        help="selector.forecast_hold [s] with --value forecast")
    parser.add_argument("--veto-patience", type=int, default=1, help="selector.veto_patience: consecutive vetoes "
                        "before physics replaces the mentor")
    parser.add_argument("--imminent-failure", type=float, default=None, help="selector.imminent_failure [s]: "
                        "a veto acts at once where the mentor's action fails this soon")
    parser.add_argument("--persistence", nargs="+", choices=["off", "latch", "always"], default=["off"],
                        help="selector.persistence with --value forecast: judge the mentor's action as it will be "
                        "repeated (latch: a veto holds until it is safe; always: at every step)")
    parser.add_argument("--references", nargs="+", choices=["physics", "physics_or_recovery"],
                        default=["physics"], help="selector.reference with --value forecast: what the mentor is "
                        "compared with (physics' action, or the better of it and braking at once)")
    parser.add_argument("--strict", nargs="+", choices=["off", "on"], default=["off"],
                        help="selector.strict_in_danger with --value forecast: no slack where physics itself fails")
    parser.add_argument("--progress-margins", type=margin_arg, nargs="+", default=[None],
                        help="selector progress_margin [m] with --value forecast (none: safety alone): the mentor's "
                        "action held 1 s must make physics' progress less this, where physics is safe")
    parser.add_argument("--latch-release-speeds", type=margin_arg, nargs="+", default=[None],
                        help="selector latch_release_speed [m/s] with --persistence latch (none: off): at most this "
                        "fast, a held veto no longer holds")
    parser.add_argument("--forecast-horizon", type=float, default=None,
                        help="the forecast's horizon [s] with --value forecast (default: SafetyForecastConfig's)")
    parser.add_argument("--hold-one-lane", action="store_true", help="selector.forecast_hold_one_lane: the hold "
                        "ends once the car has moved one lane width sideways")
    parser.add_argument("--forecast-recovery", choices=list(RECOVERIES), default=None,
                        help="the forecast's recovery with --value forecast (default: SafetyForecastConfig's)")
    parser.add_argument("--forecast-road-users", choices=list(ROAD_USER_MODELS), default=None,
                        help="how the forecast moves road users ahead (default: SafetyForecastConfig's)")
    parser.add_argument("--takeover-rates", nargs="*", metavar="DRIVER", default=None,
                        help="instead: each mentor's takeover share watching these drivers (e.g. idm-mobil-oracle "
                             "idm-mobil idm-mobil-blind random)")
    parser.add_argument("--stall-speed", type=float, default=None, help="with --takeover-rates: the mentors' "
                        "SkillProfile.stall_speed [m/s] (the stall test's speed)")
    parser.add_argument("--mentor-kwargs", nargs="+", default=[], metavar="FIELD=VALUE",
                        help="with --takeover-rates: other SkillProfile fields of the mentors (e.g. steer_tolerance=0.3)")
    parser.add_argument("--warmup", action="store_true", help="instead: the warm-up's executed actions, the mentor "
                        "alone and under the selector (selector.warmup_selection)")
    parser.add_argument("--no-floor", action="store_true", help="leave out the idm-mobil row (one run per mentor "
                        "on a long split measures it once, apart)")
    parser.add_argument("--json", type=Path, default=None)
    parser.add_argument("--resume", action="store_true", help="keep the rows --json already holds (same scenes), "
                        "measure the rest: a run cut short goes on where it stopped")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    t = time.time()
    scenes = parse_scenes(args.scenes, args.split)
    if args.resume and not args.json:
        parser.error("--resume needs --json (the file to go on from)")
    done = json.loads(args.json.read_text())["results"] if args.resume and args.json.exists() else []

    def save(results: list[dict]) -> None:
        if args.json:
            args.json.parent.mkdir(parents=True, exist_ok=True)
            args.json.write_text(json.dumps({"args": {k: str(v) if isinstance(v, Path) else v
                                                      for k, v in vars(args).items()},
                                             "results": results}, indent=2, default=str) + "\n")

    if args.warmup:
        results = warmup_rows(args.mentors, scenes, args.split, args.value, args.epsilons)
    elif args.takeover_rates is not None:
        results = takeover_rates(args.mentors, args.takeover_rates or ["idm-mobil-oracle", "idm-mobil",
                                                                       "idm-mobil-blind", "random"], scenes, args.split,
                                 mentor_kwargs(args.mentor_kwargs, args.stall_speed, parser))
    else:
        results = measure(args.mentors, scenes, args.split, args.value, args.epsilons, args.switch_margins,
                      args.variance_threshold, args.forecast_hold, args.forecast_recovery,
                          args.veto_patience, args.imminent_failure, args.hold_one_lane, args.persistence,
                          args.references, [s == "on" for s in args.strict], args.progress_margins, save,
                          floor=not args.no_floor, road_users=args.forecast_road_users, done=done,
                          latch_release_speeds=args.latch_release_speeds, forecast_horizon=args.forecast_horizon)
    print(format_table(results))
    print(f"{len(scenes)} {args.split} scenes ({scenes[0]}-{scenes[-1]}), value {args.value}, "
          f"{time.time() - t:.0f} s", flush=True)
    save(results)
    return results


if __name__ == "__main__":
    main()
