"""Each option has one source: the settings field (its docstring is the help, its default the
default) or presets.py. These tests read the commands as typer builds them."""

from dataclasses import fields

import pytest
import typer

from cubecloud_cli.cli import app
from cubecloud_cli.cli.options import build_settings, default_note, field_docs
from cubecloud_cli.cli.reference import option_annotation
from cubecloud_cli.core.runtime import Runtime
from cubecloud_cli.cunerf import CunerfSettings
from cubecloud_cli.eval import EvalSettings
from cubecloud_cli.export import ExportSettings
from cubecloud_cli.preprocess import PreprocessSettings
from cubecloud_cli.presets import DEFAULT_PRESET, PRESET_NAMES, is_preset_key, preset_default, preset_note, resolve
from cubecloud_cli.splat.settings import SplatSettings

COMMANDS = typer.main.get_command(app).commands  # type: ignore[attr-defined]
STAGE_SETTINGS = (PreprocessSettings, CunerfSettings, ExportSettings, SplatSettings)
SHARED = ("--device", "--threads", "--resume", "--force", "--quiet", "--preset", "--views", "--resolution", "--view")


def options_of(command: str) -> dict[str, object]:
    return {flag: param for param in COMMANDS[command].params for flag in param.opts}


def test_run_takes_every_option_of_preprocess_as_preprocess_reads_it():
    preprocess, run = options_of("preprocess"), options_of("run")
    assert set(preprocess) <= set(run)
    for flag, param in preprocess.items():
        assert (run[flag].help, run[flag].name, str(option_annotation("run", run[flag].name))) == (
            param.help,
            param.name,
            str(option_annotation("preprocess", param.name)),
        ), flag
    arguments = [p.name for p in COMMANDS["run"].params if type(p).__name__ == "TyperArgument"]
    assert arguments == [p.name for p in COMMANDS["preprocess"].params if type(p).__name__ == "TyperArgument"]


# eval's --output is where a comparison goes, not a work directory: -o is compared in the run test.
@pytest.mark.parametrize("flag", SHARED + tuple(sorted(set(options_of("preprocess")) - {"--output", "-o"})))
def test_a_shared_option_reads_the_same_in_every_command(flag):
    found = {name: options_of(name)[flag] for name in COMMANDS if flag in options_of(name)}
    assert found, flag
    helps = {(param.help, str(option_annotation(name, param.name)), param.default) for name, param in found.items()}
    assert len(helps) == 1, (flag, sorted(found))


def test_every_stage_option_left_unset_means_the_preset_then_the_field_default():
    for command in ("preprocess", "cunerf", "export", "splat", "eval", "run"):
        for param in COMMANDS[command].params:
            if type(param).__name__ == "TyperOption" and not param.is_flag and param.name not in ("output", "preset"):
                assert param.default is None, (command, param.name, param.default)


@pytest.mark.parametrize("settings_class", STAGE_SETTINGS + (EvalSettings, Runtime))
def test_every_option_field_has_a_docstring_and_its_help_names_its_default(settings_class):
    stage = getattr(settings_class, "STAGE", None)
    documented = field_docs(settings_class)
    helps = {param.help for command in COMMANDS.values() for param in command.params}
    for field in fields(settings_class):
        if field.name not in documented:
            continue  # a field with no option (SplatSettings' learning rates)
        note = default_note(settings_class, field.name)
        assert any(h and h.startswith(documented[field.name]) and h.endswith(note) for h in helps), field.name
        if stage and is_preset_key(stage, field.name):
            assert note == preset_note(stage, field.name)
            assert field.default == preset_default(stage, field.name)


@pytest.mark.parametrize("settings_class", STAGE_SETTINGS)
def test_the_settings_defaults_are_the_default_preset(settings_class):
    from dataclasses import asdict

    assert asdict(build_settings(settings_class, DEFAULT_PRESET, {})) == asdict(settings_class())


@pytest.mark.parametrize("preset", PRESET_NAMES)
def test_an_option_given_wins_over_the_preset_and_an_unset_one_keeps_it(preset):
    export = build_settings(ExportSettings, preset, {"views": 12, "resolution": None, "radius": None})
    assert export.views == 12 and export.resolution == resolve("export", preset, {})["resolution"]
    assert export.radius == ExportSettings().radius
    cunerf = build_settings(CunerfSettings, preset, {"model": "cunerf", "lr": None})
    assert cunerf.model == "cunerf" and cunerf.lr == resolve("cunerf", preset, {"model": "cunerf"})["lr"]


def test_help_text_holds_no_citation_of_files_outside_the_repository():
    for command in COMMANDS.values():
        for param in command.params:
            assert "DESIGN" not in (getattr(param, "help", None) or ""), (command.name, param.name)


def test_the_command_reference_shows_the_options_as_help_does():
    from conftest import REPO

    from cubecloud_cli.cli.reference import rewrite

    text = (REPO / "docs" / "commands.md").read_text()
    assert text.count("<!-- options: ") == len(COMMANDS)
    assert rewrite(text) == text, (
        "docs/commands.md is stale: run python -m cubecloud_cli.cli.reference docs/commands.md"
    )
