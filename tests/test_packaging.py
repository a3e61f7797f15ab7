"""pyproject.toml's pins agree with each other and with what is installed: each optional feature is an extra, the
``test`` extra runs every extra at a version inside that extra's range, and torch's range is bounded above."""

from __future__ import annotations

import tomllib
from importlib.metadata import requires, version
from pathlib import Path

import pytest
from packaging.requirements import Requirement
from packaging.version import Version

PROJECT = tomllib.loads((Path(__file__).resolve().parents[1] / "pyproject.toml").read_text())["project"]
EXTRAS = {name: [Requirement(r) for r in reqs] for name, reqs in PROJECT["optional-dependencies"].items()}
DEPENDENCIES = {r.name: r for r in map(Requirement, PROJECT["dependencies"])}


def test_every_optional_feature_is_an_extra_and_wandb_a_dependency():
    assert {"minari", "tensorboard", "mlflow", "sb3", "ray"} <= set(EXTRAS)
    assert {r.name for r in EXTRAS["minari"]} == {"minari"} and "hdf5" in EXTRAS["minari"][0].extras
    assert {r.name for r in EXTRAS["mlflow"]} == {"mlflow-skinny"}
    assert "wandb" in DEPENDENCIES


@pytest.mark.parametrize("extra", ["minari", "tensorboard", "mlflow", "sb3", "ray", "bench"])
def test_the_test_extra_runs_each_extra_inside_its_range(extra):
    tested = {r.name: r for r in EXTRAS["test"]}
    for req in EXTRAS[extra]:
        assert req.name in tested, f"the test extra does not install {req.name} (extra {extra})"
        pin = tested[req.name].specifier
        exact = [s.version for s in pin if s.operator == "=="]
        if exact:  # an exact pin must lie in the extra's range
            assert req.specifier.contains(exact[0]), (extra, str(req), str(pin))
        else:  # a range must be the extra's own
            assert pin == req.specifier, (extra, str(req), str(pin))


def test_torch_is_bounded_above_and_the_installed_stack_satisfies_every_pin():
    torch = DEPENDENCIES["torch"].specifier
    assert any(s.operator == "<" for s in torch), "torch needs an upper bound (torchrl<0.15 goes with it)"
    for name in ("torch", "torchrl", "tensordict", "gymnasium"):
        installed = Version(version(name)).base_version  # 2.13.0+cpu -> 2.13.0
        assert DEPENDENCIES[name].specifier.contains(installed), (name, installed)
    # torchrl's own requirement on torch is met by every torch this range allows
    torchrl_torch = next(Requirement(r) for r in requires("torchrl")
                         if Requirement(r).name == "torch" and Requirement(r).marker is None)
    lowest = next(s.version for s in torch if s.operator == ">=")
    assert torchrl_torch.specifier.contains(lowest), (str(torchrl_torch), lowest)
