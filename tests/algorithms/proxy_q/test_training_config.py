"""Tests of the recipe configuration: defaults, YAML/dict sync, profiles, overrides, validation errors."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import pytest
from omegaconf import OmegaConf

from pe_rlhf.envs.config import DrivingConfig
from pe_rlhf.runtime.config import driving_config, save_config, to_container
from pe_rlhf.runtime.config_rules import ConfigError
from pe_rlhf.runtime.config_schema import OPEN_GROUPS
from pe_rlhf.algorithms.proxy_q.builders import ensemble_fit_steps, epsilon_select
from pe_rlhf.algorithms.proxy_q.config import (
    PROFILES,
    RULES,
    algorithm_name,
    default_config_path,
    load_config,
    method_name,
    physics_config,
    validate_config,
)
from pe_rlhf.algorithms.proxy_q.config_schema import VARIANTS, RecipeConfig, defaults, variant_defaults, variant_rules

RECIPE_YAML = Path(__file__).resolve().parents[3] / "recipes" / "pe_rlhf" / "config.yaml"
HAIM_DRL_YAML = Path(__file__).resolve().parents[3] / "recipes" / "haim_drl" / "config.yaml"
GROUPS = ("env", "mentor", "physics", "selector", "collector", "replay_buffer", "optim", "loss", "disturbance",
          "logger", "eval", "checkpoint")


def leaves(d: dict, prefix: str = "") -> dict:
    out = {}
    for k, v in d.items():
        if isinstance(v, dict) and v and f"{prefix}{k}" not in OPEN_GROUPS:
            out.update(leaves(v, f"{prefix}{k}."))
        else:
            out[f"{prefix}{k}"] = v
    return out


# --------------------------------------------------------------------------- defaults and files


def test_defaults_load_and_validate_with_the_paper_values():
    """The paper's appendix values where the method keeps them; issue 41's calibrated learner (bounded proxy values,
    batch 128, half takeover rows, the actor picked on train scenes) where it replaced HACO's loss."""
    cfg = load_config()
    validate_config(cfg)
    assert set(GROUPS) <= set(cfg.keys())
    assert cfg.profile == "paper"
    assert (cfg.loss.gamma, cfg.loss.tau, cfg.optim.lr) == (0.99, 0.005, 1e-4)
    assert (cfg.loss.objective, cfg.loss.q_value_bound, cfg.replay_buffer.batch_size,
            cfg.replay_buffer.takeover_share, cfg.actor_selection.every_frames) == ("proxy_value", 1.0, 128, 0.5, 5000)
    assert (cfg.collector.frames_per_batch, cfg.collector.warmup_steps) == (100, 10000)
    paper = load_config(overrides=["loss.objective=paper"])
    assert (paper.loss.gap_coef, epsilon_select(cfg), paper.loss.psi, paper.loss.intervention_weight) == (
        10.0, -0.5, 1.0, 1.0)  # epsilon_select: null, the default value source's own (forecast: -0.5 s)
    assert cfg.selector.value == "forecast"
    assert driving_config(cfg) == DrivingConfig(lane_features=True)  # every Table-1 row uses the lane summary
    assert driving_config(cfg).split == "train"


def test_recipe_yaml_is_a_hydra_config_over_the_structured_defaults():
    """The recipe file's defaults list names the schema and the profile; its values are the schema's defaults,
    every one shown (tests/algorithms/test_recipe_config_files.py)."""
    assert default_config_path() == RECIPE_YAML
    shown = OmegaConf.to_container(OmegaConf.load(RECIPE_YAML))
    assert shown.pop("defaults") == ["pe_rlhf_schema", "_self_", {"profile": "paper"}]
    assert shown == {k: v for k, v in defaults().items() if k != "profile"}
    assert to_container(load_config()) == defaults() == OmegaConf.to_container(OmegaConf.structured(RecipeConfig))


def test_every_field_has_a_validation_rule_its_default_passes():
    variant_fields = {k for k in leaves(defaults()) if k.split(".")[0] in VARIANTS}
    assert set(leaves(defaults())) - set(OPEN_GROUPS) - variant_fields == set(RULES)
    flat = leaves(defaults())
    for field, rule in RULES.items():
        assert rule(flat[field]) is None, (field, flat[field])
    for group, spec in VARIANTS.items():  # every variant's fields, each with a rule its default passes
        for choice in spec.classes:
            values, rules = variant_defaults(group, choice), variant_rules(group, choice)
            assert set(rules) == {f"{group}.{k}" for k in values}
            for name, value in values.items():
                assert rules[f"{group}.{name}"](value) is None, (group, choice, name, value)


def test_a_variant_group_shows_its_variants_settings_and_switches_on_its_field():
    paper = load_config(overrides=["loss.objective=paper", "loss.gap_coef=5"])
    assert list(paper.loss) == list(variant_defaults("loss", "paper"))  # the proxy-value settings went
    assert paper.loss.gap_coef == 5 and paper.loss.psi == 1.0
    assert list(load_config().loss) == list(variant_defaults("loss", "proxy_value"))
    haim = load_config(overrides=["physics.enabled=false", "loss.objective=paper", "disturbance.enabled=true",
                                  "disturbance.weight=2"])
    assert list(haim.disturbance) == list(variant_defaults("disturbance", True)) and haim.disturbance.weight == 2
    assert list(load_config().disturbance) == ["enabled"]
    assert list(load_config().selector) == ["value", "epsilon_select"]  # the forecast has no ensemble
    ensemble = load_config(overrides=["selector.value=expert", "selector.num_members=2"])
    assert list(ensemble.selector) == ["value", "epsilon_select", "num_members"] and ensemble.selector.num_members == 2


def test_a_saved_config_from_before_the_settings_were_retired_still_loads(tmp_path):
    """A run folder's config.yaml written before issue 43 retired settings (loss.physics_labels, the selector's
    experiment options, the physics booleans, ...) loads for evaluation and resume, each mapped or dropped."""
    old = to_container(load_config(overrides=["loss.objective=proxy_value"]))
    old["selector"].update(enabled=True, switch_margin=None, veto_patience=1, forecast_hold=1.0, hidden=[256, 256])
    old["loss"].update(physics_labels=False, preactivation_penalty=0.0, gap_coef=10.0, fused_critics=True,
                       label_physics_action=False, td_into_takeover=False, inverting_gradients=True)
    old["physics"] = {"enabled": True, "see_obstacles": False, "stop_for_obstacles": True, "use_idm": True,
                      "use_mobil": False}
    old["collector"].update(learning_starts=100, exploration="random")
    path = tmp_path / "config.yaml"
    path.write_text(OmegaConf.to_yaml(OmegaConf.create({"algorithm": "pe-rlhf", **old})))
    cfg = load_config(path, apply_profile=False)
    assert list(cfg.loss) == list(variant_defaults("loss", "proxy_value"))
    assert (cfg.physics.model, cfg.physics.obstacles) == ("idm", "stop")
    assert "enabled" not in cfg.selector and "learning_starts" not in cfg.collector


def test_without_a_recipe_file_the_schema_defaults_are_used(monkeypatch):
    monkeypatch.setattr("pe_rlhf.algorithms.proxy_q.config.default_config_path", lambda: None)
    assert to_container(load_config()) == defaults()
    assert load_config(overrides=["profile=smoke"]).collector.total_frames == 300


def test_recipes_env_var_locates_the_file(tmp_path, monkeypatch):
    (tmp_path / "pe_rlhf").mkdir()
    (tmp_path / "pe_rlhf" / "config.yaml").write_text("optim:\n  lr: 0.002\n")
    monkeypatch.setenv("PE_RLHF_RECIPES", str(tmp_path))
    assert load_config().optim.lr == 0.002
    monkeypatch.setenv("PE_RLHF_RECIPES", str(tmp_path / "nowhere"))
    with pytest.raises(ConfigError, match="PE_RLHF_RECIPES"):
        load_config()


def test_partial_file_applies_over_defaults_and_unknown_file_key_fails(tmp_path):
    path = tmp_path / "c.yaml"
    path.write_text("mentor: {name: amateur}\nenv: {traffic_density: 0.3}\n")
    cfg = load_config(path)
    assert cfg.mentor.name == "amateur" and cfg.env.traffic_density == 0.3 and cfg.optim.lr == 1e-4
    path.write_text("optim: {learning_rate: 0.1}\n")
    with pytest.raises(ConfigError, match=r"optim\.learning_rate"):
        load_config(path)
    with pytest.raises(ConfigError, match="not found"):
        load_config(tmp_path / "missing.yaml")


def test_save_and_reload_round_trip(tmp_path):
    cfg = load_config(overrides=["profile=cpu", "optim.updates_per_batch=50", "env.horizon=500"])
    path = save_config(cfg, tmp_path / "run" / "config.yaml")
    again = load_config(path, apply_profile=False)
    assert to_container(again) == to_container(cfg)
    assert isinstance(to_container(cfg)["loss"]["hidden"], list)


def test_a_saved_config_records_the_method_and_refuses_values_that_contradict_it(tmp_path):
    haco = load_config(overrides=["profile=smoke", "physics.enabled=false", "loss.objective=paper"])
    path = save_config(haco, tmp_path / "config.yaml", algorithm_name(haco))
    assert path.read_text().startswith("algorithm: haco\n")  # the registry name, first
    assert to_container(load_config(path, apply_profile=False)) == to_container(haco)  # read apart from the values
    with pytest.raises(ConfigError, match=r"^algorithm='haco' is invalid: the run folder's config describes 'pe-rlhf'"):
        load_config(path, ["physics.enabled=true"], apply_profile=False)


# --------------------------------------------------------------------------- profiles and overrides


def test_cpu_profile_changes_the_documented_fields():
    paper, cpu = load_config(), load_config(overrides=["profile=cpu"])
    assert cpu.profile == "cpu"
    assert cpu.replay_buffer.batch_size == 256  # the paper loss's 1024 cut for 2 cores (PE-RLHF's own: 128)
    assert paper.replay_buffer.batch_size == 128
    assert cpu.optim.updates_per_batch == 100  # the paper's update-to-data ratio is kept
    assert list(cpu.loss.hidden) == [256, 256]
    assert (cpu.eval.episodes, cpu.eval.every_frames, cpu.eval.video) == (20, 10000, False)
    assert cpu.collector.total_frames == 30000


def test_quick_profile_is_make_runs_ten_minute_budget():
    quick = load_config(overrides=["profile=quick"])
    assert quick.collector.total_frames == 9000 and quick.collector.warmup_steps == 5000
    assert quick.replay_buffer.batch_size == 128 and quick.eval.video and quick.eval.every_frames == 0
    assert quick.actor_selection.every_frames == 0  # its evaluations would not fit the budget
    assert list(quick.loss.hidden) == [256, 256]  # the paper's networks


def test_smoke_profile_is_tiny():
    cfg = load_config(overrides=["profile=smoke"])
    assert cfg.collector.total_frames <= 500 and cfg.collector.warmup_steps <= 100
    assert list(cfg.loss.hidden) == [32, 32]
    assert cfg.eval.episodes == 1 and not cfg.eval.video  # filming is ~45% of a smoke run; its tests ask for it
    assert driving_config(cfg).horizon == 100


def test_profile_from_the_file_and_cli_override_on_top_of_profile(tmp_path):
    path = tmp_path / "c.yaml"
    path.write_text("profile: smoke\n")
    assert load_config(path).collector.total_frames == PROFILES["smoke"]["collector"]["total_frames"]
    cfg = load_config(path, ["replay_buffer.batch_size=64", "replay_buffer.size=5000"])
    assert cfg.replay_buffer.batch_size == 64 and cfg.profile == "smoke"
    assert load_config(path, ["profile=paper"]).collector.total_frames == 30000


@pytest.mark.parametrize("name", sorted(PROFILES))
def test_every_profile_validates_for_both_methods(name):
    validate_config(load_config(overrides=[f"profile={name}"]))
    load_config(overrides=[f"profile={name}", "physics.enabled=false"])
    load_config(overrides=[f"profile={name}", "loss.objective=proxy_value"])


def test_cli_overrides_apply():
    cfg = load_config(overrides=["optim.lr=3e-4", "mentor.name=amateur", "loss.hidden=[128,128]",
                                 "selector.value=warmup", "selector.num_members=3", "env.traffic_density=0.2",
                                 "mentor.kwargs.action_noise=0.2", "logger.backends=[csv,tensorboard]"])
    assert cfg.optim.lr == pytest.approx(3e-4)
    assert cfg.mentor.name == "amateur" and cfg.mentor.kwargs.action_noise == 0.2
    assert list(cfg.loss.hidden) == [128, 128] and cfg.selector.num_members == 3
    assert driving_config(cfg).traffic_density == 0.2
    assert driving_config(cfg, split="test").split == "test"
    assert list(cfg.logger.backends) == ["csv", "tensorboard"]


@pytest.mark.parametrize("override, named", [("optim.lrr=1", "optim.lrr"), ("optimizer.lr=1", "optimizer"),
                                             ("loss.gamma.x=1", "loss.gamma.x"), ("loss.gap_cof=5", "loss.gap_cof")])
def test_unknown_override_key_fails_naming_it(override, named):
    with pytest.raises(ConfigError, match=named.replace(".", r"\.")):
        load_config(overrides=[override])


def test_malformed_override_and_unknown_profile_fail():
    with pytest.raises(ConfigError, match="key=value"):
        load_config(overrides=["optim.lr"])
    with pytest.raises(ConfigError, match="profile='gpu'"):
        load_config(overrides=["profile=gpu"])


# --------------------------------------------------------------------------- validation


INVALID = [
    ("seed", "-1"),
    ("env.traffic_density", "-1"),
    ("env.lanes", "7"),
    ("env.trafic_density", "0.5"),
    ("mentor.name", "expert"),
    ("optim.threads", "0"),
    ("mentor.kwargs.skill", "3"),
    ("physics.model", "idm_only"),
    ("physics.obstacles", "sometimes"),
    ("selector.epsilon_select", "nan"),
    ("selector.num_members", "0"),
    ("collector.total_frames", "0"),
    ("collector.frames_per_batch", "40000"),
    ("collector.warmup_steps", "50000"),
    ("collector.backend", "threads"),
    ("collector.num_workers", "4"),
    ("replay_buffer.size", "0"),
    ("replay_buffer.batch_size", "200000"),
    ("optim.lr", "-0.001"),
    ("optim.updates_per_batch", "0"),
    ("optim.max_grad_norm", "0"),
    ("loss.gamma", "1.5"),
    ("loss.tau", "0"),
    ("loss.tau", "1.2"),
    ("loss.gap_coef", "-1"),
    ("loss.target_entropy", "high"),
    ("loss.alpha_init", "0"),
    ("loss.hidden", "[]"),
    ("loss.cosine_cost", "2"),
    ("loss.objective", "td3"),
    ("loss.q_value_bound", "0"),
    ("loss.psi", "2.0"),  # the paper loss's, set on the proxy-value loss: it would do nothing
    ("disturbance.enabled", "maybe"),
    ("disturbance.threshold", "4"),  # the disturbance cost's, with it off: it would do nothing
    ("logger.backends", "[csv,neptune]"),
    ("logger.backends", "[wandb]"),
    ("logger.project", "' '"),
    ("logger.log_every", "0"),
    ("eval.episodes", "0"),
    ("eval.split", "val"),
    ("checkpoint.keep", "0"),
    ("profile", "gpu"),
]


@pytest.mark.parametrize("field, value", INVALID)
def test_invalid_value_names_field_and_value(field, value):
    with pytest.raises(ConfigError) as info:
        load_config(overrides=[f"{field}={value}"])
    message = str(info.value)
    assert field in message, message
    assert value.strip("[]").split(",")[-1] in message, message
    assert info.value.field is None or info.value.field == field


def test_invalid_values_cover_every_group():
    assert {f.split(".")[0] for f, _ in INVALID} >= set(GROUPS)


def test_non_finite_numbers_are_refused():
    with pytest.raises(ConfigError, match=r"selector\.epsilon_select=nan is invalid: must be a finite number"):
        load_config(overrides=["selector.epsilon_select=.nan"])  # YAML's spelling, as before Hydra
    with pytest.raises(ConfigError, match=r"optim\.lr=inf is invalid: must be a finite number > 0"):
        load_config(overrides=["optim.lr=.inf"])
    with pytest.raises(ConfigError, match=r"optim\.lr=inf is invalid: must be a finite number > 0"):
        load_config(overrides=["optim.lr=inf"])  # Hydra's
    with pytest.raises(ConfigError, match=r"selector\.epsilon_select=-inf is invalid: must be a finite number"):
        load_config(overrides=["selector.epsilon_select=-.inf"])


def test_env_traffic_density_error_names_the_env_field():
    with pytest.raises(ConfigError, match=r"env\.traffic_density=-1 is invalid: must be in \[0, 5\]"):
        load_config(overrides=["env.traffic_density=-1"])


def test_ray_backend_is_refused_with_the_reason_when_not_installed():
    if importlib.util.find_spec("ray") is not None:
        load_config(overrides=["collector.backend=ray", "collector.num_workers=2"])
    else:
        with pytest.raises(ConfigError, match="ray package"):
            load_config(overrides=["collector.backend=ray", "collector.num_workers=2"])


def test_multi_process_backends_and_custom_mentor_paths_are_accepted():
    cfg = load_config(overrides=["collector.backend=multisync", "collector.num_workers=4",
                                 "mentor.name=my_pkg.mentors:CarefulMentor", "mentor.kwargs.anything=1"])
    assert cfg.collector.num_workers == 4
    with pytest.raises(ConfigError, match="mentor.name='my_pkg.mentors'"):
        load_config(overrides=["mentor.name=my_pkg.mentors"])
    with pytest.raises(ConfigError, match="collector.backend='multisync'"):
        load_config(overrides=["mentor.name=human", "collector.backend=multisync", "collector.num_workers=2"])


def test_validate_rejects_hand_built_configs_with_unknown_groups():
    cfg = load_config(validate=False)
    cfg = OmegaConf.merge(OmegaConf.create(to_container(cfg)), {"extra": {"x": 1}})
    with pytest.raises(ConfigError, match=r"extra\.x"):
        validate_config(cfg)


# --------------------------------------------------------------------------- method


def test_method_names():
    assert method_name(load_config()) == "PE-RLHF"
    assert method_name(load_config(overrides=["loss.objective=paper"])) == "PE-RLHF"  # the paper's loss
    haco = load_config(overrides=["physics.enabled=false", "loss.objective=paper"])
    assert method_name(haco) == "HACO"
    no_ensemble = load_config(overrides=["selector.value=warmup", "selector.num_members=1"])  # the ablation
    assert method_name(no_ensemble) == "PE-RLHF"
    paper = "loss.objective=paper"
    assert method_name(load_config(overrides=["physics.enabled=false", paper, "disturbance.enabled=true"])) == \
        "HAIM-DRL"
    assert method_name(load_config(overrides=["physics.enabled=false"])) == "PVP"
    assert method_name(load_config(overrides=[paper, "disturbance.enabled=true"])) == "PE-RLHF+disturbance"
    assert algorithm_name(load_config(overrides=[paper, "disturbance.enabled=true"])) == "pe-rlhf"  # a variant


def test_haim_drl_recipe_is_haco_with_the_disturbance_cost():
    cfg = load_config(HAIM_DRL_YAML)
    assert method_name(cfg) == "HAIM-DRL"
    base = leaves(defaults())
    changed = {k: v for k, v in leaves(to_container(cfg)).items() if k in base and base[k] != v}
    added = {k for k in leaves(to_container(cfg)) if k not in base}  # the disturbance group's settings, now on
    assert changed == {"physics.enabled": False, "disturbance.enabled": True, "loss.objective": "paper",
                       "replay_buffer.batch_size": 1024, "replay_buffer.takeover_share": None,
                       "actor_selection.every_frames": 0}  # HACO's learner as the paper has it
    paper_loss = {f"loss.{k}" for k in variant_defaults("loss", "paper")} - set(base)
    assert added == {f"disturbance.{k}" for k in variant_defaults("disturbance", True)} - {"disturbance.enabled"} \
        | paper_loss
    assert (cfg.disturbance.threshold, cfg.disturbance.horizon) == (5.0, 3.0)  # HAIM-DRL's 5 m/s^2
    assert (cfg.disturbance.weight, cfg.disturbance.num_qvalue_nets) == (1.0, 2)  # its own twin critic
    smoke = load_config(HAIM_DRL_YAML, ["profile=smoke", "disturbance.weight=0.5"])
    assert smoke.collector.total_frames == 300 and smoke.disturbance.weight == 0.5
    assert not load_config().disturbance.enabled  # PE-RLHF (and HACO) stay without it


def test_a_fitted_selector_needs_a_warmup_and_its_fit_scales_with_it():
    with pytest.raises(ConfigError, match="collector.warmup_steps=0"):
        load_config(overrides=["collector.warmup_steps=0", "selector.value=warmup"])
    load_config(overrides=["collector.warmup_steps=0"])  # the forecast fits nothing
    load_config(overrides=["collector.warmup_steps=0", "physics.enabled=false"])
    # the paper's 3000 gradient steps after its 10K warm-up, make run's 1500 after 5K; nothing to fit for the others
    assert ensemble_fit_steps(load_config(overrides=["selector.value=warmup"])) == 3000
    assert ensemble_fit_steps(load_config(overrides=["selector.value=warmup", "profile=quick"])) == 1500
    assert ensemble_fit_steps(load_config()) == 0
    assert ensemble_fit_steps(load_config(overrides=["selector.value=expert"])) == 0


@pytest.mark.parametrize("model, obstacles, expected", [
    ("idm_mobil", "stop", (True, True, False, True)),  # the default: IDM brakes for obstacles, MOBIL ignores them
    ("idm", "avoid", (True, False, True, True)),  # the "IDM only" ablation, seeing obstacles
    ("mobil", "blind", (False, True, False, False)),  # the "MOBIL only" ablation, blind
])
def test_physics_config_follows_the_choices(model, obstacles, expected):
    phy = physics_config(load_config(overrides=[f"physics.model={model}", f"physics.obstacles={obstacles}"]))
    assert (phy.use_idm, phy.use_mobil, phy.see_obstacles, phy.stop_for_obstacles) == expected


@pytest.mark.parametrize("overrides, expected", [
    ([], -0.5),  # the default, the physics forecast: seconds
    (["selector.value=expert"], 1.5),  # the packaged expert: the authors' threshold
    (["selector.value=warmup"], 0.5),  # the paper's table
    (["selector.value=forecast"], -0.5),  # seconds, calibrated on train scenes
    (["selector.value=forecast", "selector.epsilon_select=0.25"], 0.25),  # a set value always wins
])
def test_epsilon_select_null_takes_the_value_sources_own(overrides, expected):
    cfg = load_config(overrides=overrides)
    assert epsilon_select(cfg) == expected


def test_configuration_reference_page_is_the_rules_own_table():
    """docs/guide/configuration.md shows every field, its default and what is allowed, as the rules say it."""
    from pe_rlhf.algorithms.proxy_q.config import RULES, reference_table

    table = reference_table()
    page = (Path(__file__).resolve().parents[3] / "docs" / "guide" / "configuration.md").read_text()
    assert table in page, ("regenerate the table: python -c 'from pe_rlhf.algorithms.proxy_q.config import "
                           "reference_table; print(reference_table())'")
    variant_fields = sum(len(variant_defaults(g, c)) for g, spec in VARIANTS.items() for c in spec.classes)
    assert len(table.splitlines()) == len(RULES) + variant_fields + 2
    assert "| `optim.lr` | `0.0001` | must be a finite number > 0 |" in table
    assert "| `collector.warmup_policy` | `null` | a non-empty string, or null |" in table
