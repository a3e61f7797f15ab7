"""The entry point shared by the proxy-Q recipes (``recipes/pe_rlhf``, ``recipes/haco``, ``recipes/haim_drl``): parse the
command line, compose the recipe's config with Hydra, train, write the outputs, print the summary.

A recipe's ``train.py`` is TorchRL's layout: a ``@hydra.main`` function over its ``config.yaml`` (Hydra's
``key=value`` overrides, ``profile=cpu`` from the profile config group, ``--cfg job``, ``--help``), which hands the
composed config to :func:`hydra_task`, run through :func:`run_script`. Three flags of this package come before
Hydra sees the command line: ``--out DIR`` (the run folder; default ``runs/<method>-<time>``), ``--compare POLICY``
and ``--resume DIR [key=value ...]`` (continue the run in DIR from its saved ``config.yaml``, which is composed over
the schema without its profile). Hydra neither changes the working directory nor writes an output folder or log
(:data:`~pe_rlhf.runtime.config_compose.HYDRA_SETTINGS`). ``main(argv)`` is the same command line as a function
(tests, ``pe-rlhf sweep``). The baseline recipes (``recipes/sac_rs``, ...) use the same functions with their own
composition and training (:mod:`pe_rlhf.baselines.cli`: the ``schema``, ``load`` and ``train`` arguments).

Outputs in the run folder: ``config.yaml`` (resolved, with the method's registry name as ``algorithm:``),
``metrics.csv``, ``checkpoints/``, ``final_eval.json`` (with ``"algorithm"``), ``training_curves.png``, ``actor.pt``, ``test_episode.gif`` (with ``eval.video``) and
``reference_<policy>.json`` (with ``--compare``).

Errors, for every recipe (the baselines' ``train.py`` too): a bad config value, file or override (a
:class:`~pe_rlhf.runtime.config_rules.ConfigError`; the config is composed and checked before anything is built) or a
bad argument prints one line ``error: <message>`` to stderr and exits 2, without a traceback.
``PE_RLHF_DEBUG=1 python recipes/<method>/train.py ...`` shows the traceback instead (an environment
variable, not a flag: the command line is the run's config overrides). Called as a function,
``main(argv)`` raises the ConfigError.
"""

from __future__ import annotations

import functools
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from omegaconf import DictConfig

from pe_rlhf.evaluation import print_summary, write_json
from pe_rlhf.errors import OneLineErrorParser, debug_requested, fail
from pe_rlhf.runtime.config import save_config, to_container
from pe_rlhf.runtime.config_rules import ConfigError
from pe_rlhf.training.config import algorithm_name, finish_config, load_config, method_name
from pe_rlhf.runtime.config_compose import RecipeSchema, store_recipe_configs
from pe_rlhf.training.config_schema import PROXY_Q
from pe_rlhf.runtime.metrics_logger import MetricsLogger
from pe_rlhf.runtime.plots import plot_learning_curves
from pe_rlhf.training.trainer import evaluate_reference, registered_policies, train

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


_SCRIPT_OPTIONS = RunOptions()  # what run_script parsed, for the @hydra.main function it calls
# load(options, overrides) -> the run's validated config; train(cfg, options) -> the final evaluation
Loader = Callable[[RunOptions, list[str]], DictConfig]
Trainer = Callable[[DictConfig, RunOptions], dict]


def run_command_line(main: Callable[..., object], *args: object) -> None:
    """Run a recipe script's ``main(*args)`` (the command line is ``sys.argv``): a ConfigError becomes one
    ``error:`` line and exit code 2 (:func:`fail`), unless ``$PE_RLHF_DEBUG`` asks for the traceback."""
    try:
        main(*args)
    except ConfigError as e:
        if debug_requested():
            raise
        fail(str(e))


def option_parser(description: str | None = None, prog: str | None = None) -> RecipeArgumentParser:
    """The recipe flags (:class:`RunOptions`); everything else on the command line is Hydra's (``--help`` too,
    whose footer lists these flags)."""
    parser = RecipeArgumentParser(description=description, prog=prog, allow_abbrev=False, add_help=False)
    parser.add_argument("--out", default=None, help="output folder (default runs/<method>-<time>)")
    parser.add_argument("--compare", default=None, metavar="POLICY",
                        help="also evaluate a registered policy (e.g. idm-mobil) on the same test scenes and "
                             "print both in the final table")
    parser.add_argument("--resume", default=None, metavar="DIR", help="continue the run in DIR")
    return parser


def parse_command_line(argv: list[str], description: str | None = None) -> tuple[RunOptions, list[str]]:
    """``(options, the rest)``: the rest is Hydra's (overrides and its flags); an unknown flag fails in one line."""
    parser = option_parser(description)
    args, rest = parser.parse_known_args(argv)
    unknown = [a for a in rest if a.startswith("-") and a.split("=", 1)[0] not in HYDRA_FLAGS
               and not _is_number(a)]
    if unknown:
        parser.error(f"unrecognized arguments: {' '.join(unknown)}")
    if args.compare and args.compare not in registered_policies():  # fail now, not after training
        parser.error(f"--compare {args.compare!r}: allowed: {sorted(registered_policies())}")
    return RunOptions(args.out, args.compare, args.resume), rest


def _is_number(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def main(argv: list[str] | None = None, *, config_path: str | Path | None = None,
         description: str | None = None, load: Loader | None = None, train: Trainer | None = None) -> dict:
    """Run a recipe: ``config_path`` is its ``config.yaml`` (None: ``recipes/pe_rlhf/config.yaml``,
    see :func:`~pe_rlhf.training.config.load_config`); ``argv`` as on the command line (Hydra's flags aside).
    ``load`` and ``train`` replace :func:`load_run_config` and :func:`run` (a baseline's)."""
    options, overrides = parse_command_line(sys.argv[1:] if argv is None else list(argv), description)
    hydra_flags = [a for a in overrides if a.startswith("-") and not _is_number(a)]
    if hydra_flags:
        raise ConfigError(f"{' '.join(hydra_flags)}: Hydra's flags are for the recipe script "
                          "(python recipes/<method>/train.py), not main(argv)")
    load = load or functools.partial(load_run_config, config_path=config_path)
    return (train or run)(load(options, overrides), options)


def load_run_config(options: RunOptions, overrides: list[str], config_path: str | Path | None) -> DictConfig:
    """The run's config: with ``--resume``, the run folder's ``config.yaml`` (composed over the schema, without its
    profile) and ``overrides``; else the recipe's ``config.yaml`` composed with them."""
    if options.resume:
        return load_config(Path(options.resume) / "config.yaml", overrides=overrides, apply_profile=False)
    return load_config(config_path, overrides=overrides)


def run_script(task: Callable[[], object], config_path: str | Path, *, schema: RecipeSchema = PROXY_Q,
               load: Loader | None = None, train: Trainer | None = None) -> None:
    """A recipe script's ``__main__``: take the recipe flags (:class:`RunOptions`) off ``sys.argv``, compose and
    check the config (a ConfigError is one ``error:`` line, exit 2), then call ``task``, the script's
    ``@hydra.main`` function, which Hydra hands the composed config (:func:`hydra_task`). With ``--resume DIR``
    the run folder's config is used instead, without Hydra's command line. ``schema`` is the structured config
    the script's ``config.yaml`` names; ``load`` and ``train`` replace :func:`load_run_config` and :func:`run`."""
    global _SCRIPT_OPTIONS
    store_recipe_configs(schema)
    load = load or functools.partial(load_run_config, config_path=config_path)
    try:
        options, rest = parse_command_line(sys.argv[1:])
        hydra_flags = [a for a in rest if a.startswith("-") and not _is_number(a)]
        if options.resume or not hydra_flags:  # composed here first, so that a bad value is one line
            cfg = load(options, rest)
        if options.resume:
            (train or run)(cfg, options)
            return
        _SCRIPT_OPTIONS = options
        sys.argv = [sys.argv[0], *rest]
        store_recipe_configs(schema)  # its profile group, whichever family load composed last
        task()
    except ConfigError as e:
        if debug_requested():
            raise
        fail(str(e))


def hydra_task(cfg: DictConfig, *, finish: Callable[[DictConfig, list[str]], DictConfig] = finish_config,
               train: Trainer | None = None) -> dict:
    """The body of a recipe's ``@hydra.main`` function: ``finish`` the composed ``cfg`` (the proxy-Q recipes':
    ``mentor.name=human``'s defaults; every rule), then :func:`run` (or ``train``) it with the flags
    :func:`run_script` took."""
    from hydra.core.hydra_config import HydraConfig

    overrides = list(HydraConfig.get().overrides.task) if HydraConfig.initialized() else []
    try:
        cfg = finish(cfg, overrides)
    except ConfigError as e:
        if debug_requested():
            raise
        fail(str(e))
    return (train or run)(cfg, _SCRIPT_OPTIONS)


def run(cfg: DictConfig, options: RunOptions = RunOptions()) -> dict:
    """Train a validated ``cfg`` into ``options.out`` (or continue the run in ``options.resume``), write the
    outputs, print the final table."""
    method = method_name(cfg)
    if options.resume:
        out = Path(options.resume)
    else:
        out = Path(options.out or cfg.logger.out_dir or f"runs/{method.lower()}-{time.strftime('%Y%m%d-%H%M%S')}")
        out.mkdir(parents=True, exist_ok=True)
        save_config(cfg, out / "config.yaml", algorithm_name(cfg))
    resume = bool(options.resume)
    with MetricsLogger(out, csv=bool(cfg.logger.csv), wandb=bool(cfg.logger.wandb), wandb_mode=str(cfg.logger.wandb_mode),
                       wandb_project=str(cfg.logger.wandb_project), tensorboard=bool(cfg.logger.tensorboard),
                       mlflow=bool(cfg.logger.mlflow),
                       config=to_container(cfg), resume=resume) as logger:
        final = train(cfg, out, logger, checkpoint_dir=out / "checkpoints", resume=resume)
    write_json(out / "final_eval.json", final)
    plot_learning_curves(out / "metrics.csv", out, warmup_steps=int(cfg.collector.warmup_steps))
    report_final(out, method, final, options.compare, cfg)
    return final


def report_final(out: Path, name: str, final: dict, compare: str | None, cfg) -> None:
    """Print the final table (with ``compare``, a reference policy on the same scenes, saved as
    ``reference_<policy>.json``) and where the outputs are; shared by every recipe's entry point."""
    rows = [(name, final)]
    if compare:
        reference = evaluate_reference(compare, cfg)
        write_json(out / f"reference_{compare}.json", reference)
        rows.insert(0, (compare, reference))
    print_summary(rows)
    print(f"outputs in {out}")
