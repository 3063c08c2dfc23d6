"""One place for every name and default (vrnet_ext.names): the command line's choices and defaults
come from it, and the library's errors name arguments, not flags."""
import ast
import subprocess
import sys
from pathlib import Path

import vrnet_ext
from vrnet_ext import names

PACKAGE = Path(vrnet_ext.__file__).parent
CHOSEN = {value for value in vars(names).values() if isinstance(value, str)} | {
    item for value in vars(names).values() if isinstance(value, tuple) for item in value}


def add_argument_calls(path: Path):
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Call) and getattr(node.func, "attr", getattr(node.func, "id", "")) in (
                "add_argument", "add"):
            yield node


def test_command_line_choices_and_defaults_come_from_the_names_module():
    """No ``choices=`` spelled out as a literal list, and no default typed as a string that is one
    of the names (a method, backend, split, setting, ICP step, shipped model)."""
    found = []
    for path in sorted((PACKAGE / "cli").glob("*.py")):
        for call in add_argument_calls(path):
            for keyword in call.keywords:
                value = keyword.value
                if keyword.arg == "choices" and isinstance(value, (ast.Tuple, ast.List, ast.Set)):
                    found.append(f"{path.name}:{call.lineno} choices={ast.unparse(value)}")
                if keyword.arg == "default" and isinstance(value, ast.Constant) and value.value in CHOSEN:
                    found.append(f"{path.name}:{call.lineno} default={value.value!r}")
    assert not found, found


def test_library_errors_name_arguments_not_flags():
    """Outside ``cli/``, no message raised as an exception names a command-line flag (``--...``);
    the command line translates argument names into its flags (``cli.common.as_flags``)."""
    found = []
    for path in sorted(PACKAGE.rglob("*.py")):
        if "cli" in path.relative_to(PACKAGE).parts:
            continue
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Raise) and node.exc is not None:
                text = " ".join(c.value for c in ast.walk(node.exc) if isinstance(c, ast.Constant)
                                and isinstance(c.value, str))
                if " --" in text or text.startswith("--") or "(--" in text:
                    found.append(f"{path.relative_to(PACKAGE)}:{node.lineno}: {text[:80]}")
    assert not found, found


def test_the_names_module_imports_nothing():
    code = "import sys, vrnet_ext.names; print(sorted(m for m in sys.modules if m.startswith(('torch', 'numpy'))))"
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0 and done.stdout.strip() == "[]", done.stdout + done.stderr


def test_every_yes_no_option_is_a_switch_and_the_old_styles_still_work_with_a_warning(capsys):
    """One style for yes/no options in every command: --name / --no-name. The 0.1 forms (--name 0,
    --fpfh, --fpfh-points) still parse, hidden, and say the new spelling."""
    import argparse

    import pytest

    from vrnet_ext.cli import build_parser, build_train_config
    from vrnet_ext.cli.common import Switch

    commands = [a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction)][0].choices
    switches = 0
    for name, command in commands.items():
        for action in command._actions:
            shown = action.help is not argparse.SUPPRESS
            if shown and (action.nargs == 0 or isinstance(action, Switch)) and action.dest != "help":
                assert isinstance(action, Switch) and len(action.option_strings) == 2, (name, action.option_strings)
                switches += 1
    assert switches >= 10, switches
    parse = build_parser().parse_args
    config = build_train_config(parse(["train", "--preset", "tiny", "--no-flush-denormal", "--walk-gate",
                                       "--no-progress"]))
    assert (config.runtime.flush_denormal, config.model["walk_gate"], config.runtime.progress) == (False, True, False)
    assert "warning" not in capsys.readouterr().err
    old = build_train_config(parse(["train", "--preset", "tiny", "--flush-denormal", "0", "--walk-gate", "1"]))
    assert old.runtime == config.runtime.__class__(**{**vars(config.runtime), "progress": True})
    assert old.model == config.model
    err = capsys.readouterr().err
    assert "--flush-denormal 0 is now --no-flush-denormal" in err and "--walk-gate 1 is now --walk-gate" in err
    with pytest.raises(SystemExit):
        parse(["train", "--flush-denormal", "maybe"])
    assert "takes no value (--flush-denormal or --no-flush-denormal), got 'maybe'" in capsys.readouterr().err
    assert parse(["register", "a.ply", "b.ply", "--fpfh-points", "500"]).global_points == 500
    assert "--fpfh-points is now --global-points" in capsys.readouterr().err
    for option in ("--fpfh-points", "--fpfh "):
        with pytest.raises(SystemExit):
            parse(["register", "--help"])
        assert option not in capsys.readouterr().out
