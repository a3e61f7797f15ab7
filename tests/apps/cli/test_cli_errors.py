"""Users' entry points: a bad config value or argument is one ``error:`` line and exit code 2 (no traceback),
``--debug`` / ``PE_RLHF_DEBUG=1`` shows the traceback; ``pe-rlhf --help`` and ``--version``.

The subprocess tests run the real commands (``python recipes/<method>/train.py``, ``pe-rlhf``); every
error here happens while the config is checked, before any env is built, so each takes the import time.
"""

from __future__ import annotations

import os
import runpy
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

import pe_rlhf
from pe_rlhf.apps.cli import SUBCOMMANDS, build_parser
from pe_rlhf.apps.cli import main as cli_main
from _scripts import SCRIPT_ENV, run_recipe_here

ROOT = Path(__file__).resolve().parents[3]
RECIPES = sorted(p.parent.name for p in (ROOT / "recipes").glob("*/train.py"))
ENV = {**os.environ, "PYTHONPATH": SCRIPT_ENV["PYTHONPATH"], "SDL_VIDEODRIVER": "dummy", "OMP_NUM_THREADS": "1"}
ENV.pop("PE_RLHF_DEBUG", None)


def run(*argv: str, **env: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, *argv], cwd=ROOT, env={**ENV, **env}, capture_output=True, text=True,
                          timeout=300, check=False)


def pe_rlhf_command() -> list[str]:
    """The installed ``pe-rlhf`` console script beside this interpreter, else ``python -m pe_rlhf.apps.cli``."""
    script = Path(sys.executable).with_name("pe-rlhf")
    return [str(script)] if script.exists() else [sys.executable, "-m", "pe_rlhf.apps.cli"]


# -- recipes: the real command line ------------------------------------------------------------------
def test_recipe_config_error_is_one_line_and_exit_code_2(tmp_path):
    out = tmp_path / "run"
    proc = run("recipes/pe_rlhf/train.py", "optim.lr=abc", "--out", str(out))  # a fresh process, as a user runs it
    assert proc.returncode == 2, proc.stderr[-2000:]
    assert proc.stderr == "error: optim.lr='abc' is invalid: must be a finite number > 0\n"
    assert not out.exists()  # nothing was started


@pytest.mark.parametrize("recipe, override, message", [
    ("pe_rlhf", "mentor.name=nobody", "error: mentor.name='nobody' is invalid: allowed: ['adversarial', "),
    ("sac_rs", "foo.bar=1", "error: unknown config key 'foo.bar' (command-line override): the config has no 'foo'"),
])
def test_recipe_config_errors_name_the_field_the_value_and_what_is_allowed(tmp_path, monkeypatch, capsys, recipe,
                                                                          override, message):
    out = tmp_path / "run"
    code, _, err = run_recipe_here(recipe, override, "--out", str(out), monkeypatch=monkeypatch, capsys=capsys)
    assert code == 2 and err.count("\n") == 1 and err.startswith(message), err
    assert not out.exists()


def test_recipe_debug_env_var_shows_the_traceback(monkeypatch):
    from pe_rlhf.runtime.config_rules import ConfigError

    script = ROOT / "recipes" / "pe_rlhf" / "train.py"
    monkeypatch.setenv("PE_RLHF_DEBUG", "1")
    monkeypatch.setattr(sys, "argv", [str(script), "optim.lr=abc"])
    with pytest.raises(ConfigError, match=r"^optim.lr='abc' is invalid: must be a finite number > 0$"):
        runpy.run_path(str(script), run_name="__main__")  # raised, not turned into one line: Python prints it


def test_negative_epsilon_select_is_accepted_and_the_message_states_the_range():
    """A negative ``epsilon_select`` is physics as a veto (kept valid); the rule says what each sign does."""
    from pe_rlhf.runtime.config_rules import ConfigError
    from pe_rlhf.algorithms.proxy_q.config import load_config

    assert load_config(overrides=["selector.epsilon_select=-1"]).selector.epsilon_select == -1
    with pytest.raises(ConfigError) as info:
        load_config(overrides=["selector.epsilon_select=high"])
    text = str(info.value)
    assert text.startswith("selector.epsilon_select='high' is invalid: must be a finite number (any sign")
    assert "> 0" in text and "< 0 physics vetoes the mentor" in text


# -- every recipe's __main__, in this process (the imports are paid once) ----------------------------------
@pytest.mark.parametrize("recipe", RECIPES)
def test_every_recipe_script_reports_a_config_error_in_one_line(recipe, tmp_path, monkeypatch, capsys):
    script = ROOT / "recipes" / recipe / "train.py"
    monkeypatch.delenv("PE_RLHF_DEBUG", raising=False)
    monkeypatch.setattr(sys, "argv", [str(script), "foo.bar=1", "--out", str(tmp_path / "run")])
    with pytest.raises(SystemExit) as info:
        runpy.run_path(str(script), run_name="__main__")
    err = capsys.readouterr().err
    assert info.value.code == 2 and err.startswith("error: unknown config key 'foo.bar'") and err.count("\n") == 1
    assert not (tmp_path / "run").exists()
    monkeypatch.setattr(sys, "argv", [str(script), "--no-such-flag"])  # argparse's own errors: one line too
    with pytest.raises(SystemExit) as info:
        runpy.run_path(str(script), run_name="__main__")
    assert info.value.code == 2 and capsys.readouterr().err == "error: unrecognized arguments: --no-such-flag\n"


def test_recipe_main_called_as_a_function_still_raises():
    """Tests, sweeps and notebooks call ``main(argv)``: they get the ConfigError, not an exit."""
    from pe_rlhf.algorithms.baselines import main as baseline_main
    from pe_rlhf.runtime.config_rules import ConfigError
    from _scripts import load_pe_rlhf_recipe

    recipe = load_pe_rlhf_recipe()
    with pytest.raises(ConfigError, match="optim.lr='abc'"):
        recipe.main(["optim.lr=abc"])
    with pytest.raises(ConfigError, match="foo.bar"):
        baseline_main("bc", ["foo.bar=1"])


# -- the pe-rlhf command ---------------------------------------------------------------------------------
def test_pe_rlhf_bad_value_is_one_line_and_exit_code_2():
    proc = subprocess.run([*pe_rlhf_command(), "evaluate", "--config-override", "lanes=7", "--no-progress"],
                          cwd=ROOT, env=ENV, capture_output=True, text=True, timeout=300, check=False)
    assert proc.returncode == 2, proc.stderr[-2000:]
    assert proc.stderr == "error: DrivingConfig.lanes=7 is invalid: must be 2, 3 or 4\n"


@pytest.mark.parametrize("argv, message", [
    (["demo", "record", "--mentor", "nobody", "--steps", "5", "--out", "unused"], "error: --mentor 'nobody': "),
    (["evaluate", "--episodes", "abc"], "error: argument --episodes: invalid int value: 'abc'"),
    (["evaluate", "--seeds", "1000-1001", "--episodes", "5"], "error: --episodes 5: --seeds 1000-1001 has 2 seeds"),
    (["nosuchcommand"], "error: argument COMMAND: invalid choice: 'nosuchcommand'"),
])
def test_pe_rlhf_errors_are_one_line(argv, message, monkeypatch, capsys):
    monkeypatch.delenv("PE_RLHF_DEBUG", raising=False)
    with pytest.raises(SystemExit) as info:
        cli_main(argv)
    err = capsys.readouterr().err
    assert info.value.code == 2 and err.startswith(message) and err.count("\n") == 1, err


@pytest.mark.parametrize("argv", [["--debug", "evaluate", "--config-override", "lanes=7"],
                                  ["evaluate", "--config-override", "lanes=7", "--debug"]])
def test_pe_rlhf_debug_raises_the_error_itself(argv, monkeypatch):
    monkeypatch.delenv("PE_RLHF_DEBUG", raising=False)
    with pytest.raises(ValueError, match=r"DrivingConfig\.lanes=7 is invalid"):
        cli_main(argv)


def test_pe_rlhf_debug_env_var(monkeypatch):
    monkeypatch.setenv("PE_RLHF_DEBUG", "1")
    with pytest.raises(ValueError, match=r"DrivingConfig\.lanes=7 is invalid"):
        cli_main(["evaluate", "--config-override", "lanes=7"])


def test_pe_rlhf_help_describes_the_tool_with_an_example_per_subcommand():
    text = build_parser().format_help()
    assert "SUBCOMMANDS" not in text and "register" not in text
    assert text.count("PE-RLHF") >= 1 and "recipes/<method>/train.py" in text
    for name in SUBCOMMANDS:
        assert f"\n  pe-rlhf {name} " in text, name  # an example line in the epilog
        assert f"\n    {name} " in text, name  # argparse's list of commands with their help
    assert "--debug" in text and "--version" in text


# -- one version source ----------------------------------------------------------------------------------
def pyproject_version() -> str:
    with open(ROOT / "pyproject.toml", "rb") as f:
        project = tomllib.load(f)["project"]
    assert project["name"] == pe_rlhf.DISTRIBUTION
    return project["version"]


def test_version_comes_from_the_distribution_metadata():
    from importlib.metadata import version

    assert pe_rlhf.__version__ == version("pe-rlhf") == pyproject_version()


def test_version_in_an_uninstalled_source_checkout_reads_pyproject(tmp_path):
    """A fresh checkout (no ``*.egg-info``) run with ``python -S`` (no site-packages: the installed
    distribution is invisible): ``__version__`` is its own pyproject.toml's."""
    checkout = tmp_path / "checkout"
    (checkout / "src" / "pe_rlhf").mkdir(parents=True)
    (checkout / "src" / "pe_rlhf" / "__init__.py").write_text((ROOT / "src" / "pe_rlhf" / "__init__.py").read_text())
    (checkout / "pyproject.toml").write_text('[project]\nname = "pe-rlhf"\nversion = "9.8.7"\n')
    code = ("import sys; sys.path.insert(0, sys.argv[1]); import importlib.metadata as m, pe_rlhf\n"
            "try:\n    m.version('pe-rlhf'); print('installed')\n"
            "except m.PackageNotFoundError:\n    print(pe_rlhf.__version__)")
    proc = subprocess.run([sys.executable, "-S", "-c", code, str(checkout / "src")], capture_output=True, text=True,
                          timeout=60, check=True)
    assert proc.stdout.strip() == "9.8.7"


def test_pe_rlhf_version(capsys):
    with pytest.raises(SystemExit) as info:
        cli_main(["--version"])
    assert info.value.code == 0 and capsys.readouterr().out == f"pe-rlhf {pyproject_version()}\n"
    proc = subprocess.run([*pe_rlhf_command(), "--version"], env=ENV, capture_output=True, text=True, timeout=120,
                          check=False)
    assert proc.returncode == 0 and proc.stdout == f"pe-rlhf {pe_rlhf.__version__}\n"
