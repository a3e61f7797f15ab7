"""The command line every recipe's ``train.py`` shares: the recipe flags, Hydra's composition, the errors, the final
table. It knows no method: each family plugs in how its config is loaded and how it trains.

A recipe's ``train.py`` is TorchRL's layout: a ``@hydra.main`` function over its ``config.yaml`` (Hydra's
``key=value`` overrides, ``profile=cpu`` from the profile config group, ``--cfg job``, ``--help``), which hands the
composed config to :func:`hydra_task`, run through :func:`run_script`. Three flags of this package come before
Hydra sees the command line: ``--out DIR`` (the run folder; default ``runs/<method>-<time>``), ``--compare POLICY``
(a registered policy on the same test scenes: :func:`evaluate_reference`) and ``--resume DIR [key=value ...]``
(continue the run in DIR from its saved ``config.yaml``, which is composed over the schema without its profile).
Hydra neither changes the working directory nor writes an output folder or log
(:data:`~pe_rlhf.runtime.config_compose.HYDRA_SETTINGS`). :func:`main` is the same command line as a function
(tests, ``pe-rlhf sweep``).

What a family plugs in: its :class:`~pe_rlhf.runtime.config_compose.RecipeSchema` (``schema``), ``load`` (the run's
validated config from the flags and the overrides), ``finish`` (what follows Hydra's composition) and ``train`` (the
run, its outputs written, :func:`report_final` printed): the proxy-Q recipes' in
:mod:`pe_rlhf.algorithms.proxy_q.recipe`, the baselines' in :mod:`pe_rlhf.algorithms.baselines.cli`.

Errors, for every recipe (the baselines' ``train.py`` too): a bad config value, file or override (a
:class:`~pe_rlhf.runtime.config_rules.ConfigError`; the config is composed and checked before anything is built), a
bad argument, or a failure at run time that a user can cause (:data:`RUNTIME_FAILURES`: a corrupt checkpoint, a full
disk, a read-only run folder, a run folder another run holds, a non-finite loss, memory) prints one line
``error: <message>`` to stderr and exits 2, without a traceback. ``--debug`` (or
``PE_RLHF_DEBUG=1 python recipes/<method>/train.py ...``) shows the traceback instead. Called as a function,
``main(argv)`` raises the exception.
"""

from __future__ import annotations

import argparse
import os
import sys
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from omegaconf import DictConfig

from pe_rlhf.errors import DEBUG_ENV_VAR, OneLineErrorParser, debug_requested, fail
from pe_rlhf.evaluation import Policy, evaluate, make_policy, print_summary, write_json
from pe_rlhf.runtime.config_compose import RecipeSchema, store_recipe_configs
from pe_rlhf.runtime.config_rules import ConfigError
from pe_rlhf.transforms.shield import DEFAULT_THRESHOLD as SHIELD_THRESHOLD  # --shield's default

# Hydra's own flags a recipe passes on to @hydra.main (an unknown flag is an error here, in one line).
HYDRA_FLAGS = ("--cfg", "-c", "--help", "-h", "--hydra-help", "--info", "-i", "--resolve", "--package", "-p",
               "--version", "--config-path", "-cp", "--config-name", "-cn", "--config-dir", "-cd", "--multirun",
               "-m", "--shell-completion", "-sc")


class RecipeArgumentParser(OneLineErrorParser):
    """A recipe's parser: one-line errors (:class:`~pe_rlhf.errors.OneLineErrorParser`), the traceback with
    ``$PE_RLHF_DEBUG``."""


@dataclass(frozen=True)
class RunOptions:
    """The flags a recipe takes beside its config overrides."""

    out: str | None = None
    compare: str | None = None
    resume: str | None = None
    shield: float | None = None  # [s]: also evaluate the trained actor under the runtime shield


_SCRIPT_OPTIONS = RunOptions()  # what run_script parsed, for the @hydra.main function it calls
# load(options, overrides) -> the run's validated config; train(cfg, options) -> the final evaluation
Loader = Callable[[RunOptions, list[str]], DictConfig]
# What a user's command, file or machine can make a run raise (programming errors keep their traceback).
RUNTIME_FAILURES = (ConfigError, OSError, ValueError, FloatingPointError, MemoryError, RuntimeError)
Trainer = Callable[[DictConfig, RunOptions], dict]


def run_command_line(main: Callable[..., object], *args: object) -> None:
    """Run a recipe script's ``main(*args)`` (the command line is ``sys.argv``): a ConfigError or a runtime
    failure becomes one ``error:`` line and exit code 2 (:func:`fail`), unless ``--debug`` or ``$PE_RLHF_DEBUG``
    asks for the traceback."""
    try:
        main(*args)
    except RUNTIME_FAILURES as e:
        fail_in_one_line(e)


def fail_in_one_line(error: BaseException) -> None:
    """Re-raise ``error`` with ``--debug``/``$PE_RLHF_DEBUG``; else print it as one ``error:`` line and exit 2
    (a ConfigError as it is, anything else with its type, and where the traceback is)."""
    if debug_requested():
        raise error
    if isinstance(error, ConfigError):
        fail(str(error))
    text = str(error) or "(no message)"
    fail(f"{type(error).__name__}: {text} (--debug shows the traceback)")


def option_parser(description: str | None = None, prog: str | None = None) -> RecipeArgumentParser:
    """The recipe flags (:class:`RunOptions`); everything else on the command line is Hydra's (``--help`` too,
    whose footer lists these flags)."""
    parser = RecipeArgumentParser(description=description, prog=prog, allow_abbrev=False, add_help=False)
    parser.add_argument("--out", default=None, help="output folder (default runs/<method>-<time>)")
    parser.add_argument("--compare", default=None, metavar="POLICY",
                        help="also evaluate a registered policy (e.g. idm-mobil) on the same test scenes and "
                             "print both in the final table")
    parser.add_argument("--resume", default=None, metavar="DIR", help="continue the run in DIR")
    parser.add_argument("--shield", nargs="?", type=_shield_threshold, const=SHIELD_THRESHOLD, default=None,
                        metavar="SECONDS",
                        help="also evaluate the trained actor under the runtime safety shield (threshold, default "
                             "0.5 s: docs/guide/shield.md) on the same scenes, a row of the final table")
    parser.add_argument("--debug", action="store_true",
                        help="show the traceback of an error instead of one line (as PE_RLHF_DEBUG=1)")
    return parser


def parse_command_line(argv: list[str], description: str | None = None) -> tuple[RunOptions, list[str]]:
    """``(options, the rest)``: the rest is Hydra's (overrides and its flags); an unknown flag fails in one line."""
    parser = option_parser(description)
    # a bare --shield before an override (--shield profile=smoke): the default threshold, not the override's text
    argv = [f"--shield={SHIELD_THRESHOLD}" if a == "--shield" and (i + 1 == len(argv) or not _is_number(argv[i + 1]))
            else a for i, a in enumerate(argv)]
    args, rest = parser.parse_known_args(argv)
    unknown = [a for a in rest if a.startswith("-") and a.split("=", 1)[0] not in HYDRA_FLAGS
               and not _is_number(a)]
    if unknown:
        parser.error(f"unrecognized arguments: {' '.join(unknown)}")
    if args.debug:  # one switch for every layer below (errors.debug_requested reads it)
        os.environ[DEBUG_ENV_VAR] = "1"
    if args.compare and args.compare not in registered_policies():  # fail now, not after training
        parser.error(f"--compare {args.compare!r}: allowed: {sorted(registered_policies())}")
    return RunOptions(args.out, args.compare, args.resume, args.shield), rest


def _shield_threshold(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        value = -1.0
    if not value >= 0 or value == float("inf"):
        raise argparse.ArgumentTypeError(f"{text!r}: a threshold in seconds >= 0 (e.g. 0.5)")
    return value


def _is_number(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def main(argv: list[str] | None, *, load: Loader, train: Trainer, description: str | None = None) -> dict:
    """Run a recipe: ``argv`` as on the command line (Hydra's flags aside; None: ``sys.argv[1:]``); ``load``
    composes and checks the run's config from the flags and the overrides, ``train`` runs it."""
    options, overrides = parse_command_line(sys.argv[1:] if argv is None else list(argv), description)
    hydra_flags = [a for a in overrides if a.startswith("-") and not _is_number(a)]
    if hydra_flags:
        raise ConfigError(f"{' '.join(hydra_flags)}: Hydra's flags are for the recipe script "
                          "(python recipes/<method>/train.py), not main(argv)")
    return train(load(options, overrides), options)


def run_script(task: Callable[[], object], *, schema: RecipeSchema, load: Loader, train: Trainer) -> None:
    """A recipe script's ``__main__``: take the recipe flags (:class:`RunOptions`) off ``sys.argv``, compose and
    check the config (a ConfigError is one ``error:`` line, exit 2), then call ``task``, the script's
    ``@hydra.main`` function, which Hydra hands the composed config (:func:`hydra_task`). With ``--resume DIR``
    the run folder's config is used instead, without Hydra's command line. ``schema`` is the structured config
    the script's ``config.yaml`` names; ``load`` composes and checks the run's config, ``train`` runs it."""
    global _SCRIPT_OPTIONS
    store_recipe_configs(schema)
    try:
        options, rest = parse_command_line(sys.argv[1:])
        hydra_flags = [a for a in rest if a.startswith("-") and not _is_number(a)]
        if options.resume or not hydra_flags:  # composed here first, so that a bad value is one line
            cfg = load(options, rest)
        if options.resume:
            train(cfg, options)
            return
        _SCRIPT_OPTIONS = options
        sys.argv = [sys.argv[0], *rest]
        store_recipe_configs(schema)  # its profile group, whichever family load composed last
        task()
    except RUNTIME_FAILURES as e:
        fail_in_one_line(e)


def hydra_task(cfg: DictConfig, *, finish: Callable[[DictConfig, list[str]], DictConfig], train: Trainer) -> dict:
    """The body of a recipe's ``@hydra.main`` function: ``finish`` the composed ``cfg`` given Hydra's overrides
    (the proxy-Q recipes': ``mentor.name=human``'s defaults, then every rule), then ``train`` it with the flags
    :func:`run_script` took."""
    from hydra.core.hydra_config import HydraConfig

    overrides = list(HydraConfig.get().overrides.task) if HydraConfig.initialized() else []
    try:
        return train(finish(cfg, overrides), _SCRIPT_OPTIONS)
    except RUNTIME_FAILURES as e:  # inside Hydra's job: its own handler would print the traceback
        fail_in_one_line(e)


def report_final(out: Path, name: str, final: dict, cfg, options: RunOptions = RunOptions(),
                 policy: Callable[[], Policy] | None = None) -> None:
    """Print the final table and where the outputs are; shared by every recipe's entry point. With
    ``options.compare``, a reference policy on the same scenes (saved as ``reference_<policy>.json``); with
    ``options.shield``, the trained actor (``policy()``) under the runtime shield on them too (saved as
    ``shielded_eval.json``, with the share of steps the shield drove)."""
    rows = [(name, final)]
    if options.shield is not None and policy is not None:
        shielded = evaluate_shielded(policy(), float(options.shield), cfg, name=f"{name} shielded")
        write_json(out / SHIELDED_EVAL, shielded)
        rows.append((f"{name} shielded", shielded))
    picking = final.get("actor_selection")
    if picking is not None:  # the last actor's row above the picked one's
        rows.insert(0, ("last", final["last_actor"]))
    if options.compare:
        reference = evaluate_reference(options.compare, cfg)
        write_json(out / f"reference_{options.compare}.json", reference)
        rows.insert(0, (options.compare, reference))
    print_summary(rows)
    if options.shield is not None and policy is not None:
        print(f"{name} shielded: the shield drove {shielded['override_share']:.3f} of the steps (threshold "
              f"{float(options.shield):g} s, a decision {shielded['decision_latency_ms']['mean']:.1f} ms)")
    if picking is not None:
        step, last = picking["picked_step"], max(map(int, picking["scores"]))
        score = picking["scores"][str(step)]
        print(f"{name}: the actor of frame {step}, picked on {picking['episodes']} train scenes (success "
              f"{score['success_rate']:.2f}, route completion {score['route_completion']:.2f}); 'last': the actor "
              f"of frame {last}")
    print(f"outputs in {out}")


def registered_policies() -> list[str]:
    """Names :func:`evaluate_reference` accepts (the evaluation registry, mentors included)."""
    import pe_rlhf.mentors.registry  # noqa: F401
    from pe_rlhf.evaluation import POLICY_FACTORIES

    return list(POLICY_FACTORIES)


SHIELDED_EVAL = "shielded_eval.json"


def evaluate_shielded(policy: Policy, threshold: float, cfg, name: str) -> dict:
    """``policy`` under :class:`~pe_rlhf.wrappers.SafetyShieldWrapper` (``threshold`` seconds) on the final
    evaluation's scenes (``eval.split``, ``eval.episodes``)."""
    from pe_rlhf.envs import scene_seeds
    from pe_rlhf.runtime.config import driving_config
    from pe_rlhf.wrappers import SafetyShieldWrapper

    seeds = scene_seeds(str(cfg.eval.split))[: int(cfg.eval.episodes)]
    return evaluate(policy, seeds, driving_config(cfg), progress=False, name=name,
                    wrap_env=lambda env: SafetyShieldWrapper(env, threshold)).to_dict()


def evaluate_reference(policy_name: str, cfg, episodes: int | None = None) -> dict:
    """A registered policy (e.g. ``idm-mobil``) on the same ``eval.split`` seeds as
    :func:`~pe_rlhf.runtime.run.evaluate_actor`, for the comparison table printed after training
    (``train.py --compare idm-mobil``)."""
    import pe_rlhf.mentors.registry  # noqa: F401  (registers the mentors as evaluation policies)
    from pe_rlhf.envs import scene_seeds
    from pe_rlhf.runtime.config import driving_config

    seeds = scene_seeds(str(cfg.eval.split))[: int(episodes or cfg.eval.episodes)]
    return evaluate(make_policy(policy_name, int(cfg.seed)), seeds, driving_config(cfg), progress=False,
                    name=policy_name).to_dict()
