import subprocess
import sys

from colmap_miho.cli import main


def test_help_does_not_import_torch():
    code = (
        "import sys\n"
        "from colmap_miho.cli import build_parser\n"
        "build_parser().format_help()\n"
        "assert 'torch' not in sys.modules, 'torch imported by --help'\n"
        "assert 'pycolmap' not in sys.modules, 'pycolmap imported by --help'\n"
    )
    subprocess.run([sys.executable, "-c", code], check=True)


def test_module_entry_point_help():
    out = subprocess.run([sys.executable, "-m", "colmap_miho", "--help"], capture_output=True, text=True, check=True)
    assert "colmap-miho" in out.stdout


def test_no_command_prints_help_and_fails(capsys):
    assert main([]) == 2
    assert "usage" in capsys.readouterr().out


def _failing_report(monkeypatch, exc: BaseException) -> None:
    """Make the ``report`` command raise ``exc`` as soon as it runs (paths checked first)."""
    import colmap_miho.commands.report as report_command

    def run(args):
        raise exc

    monkeypatch.setattr(report_command, "run", run)


def test_user_error_exits_2_on_one_line(monkeypatch, tmp_path, capsys):
    from colmap_miho.errors import InvalidInput

    _failing_report(monkeypatch, InvalidInput("filter.t_l must be > 0, got -1"))
    assert main(["report", "--model", str(tmp_path)]) == 2
    assert capsys.readouterr().err.strip().splitlines() == ["ERROR: filter.t_l must be > 0, got -1"]


def test_internal_value_error_exits_1_with_the_verbose_hint(monkeypatch, tmp_path, capsys):
    _failing_report(monkeypatch, ValueError("operands could not be broadcast together"))
    assert main(["report", "--model", str(tmp_path)]) == 1
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 1 and "ValueError: operands could not be broadcast together" in lines[0]
    assert "run with -v" in lines[0] and "report it" in lines[0]


# --------------------------------------------------------------------------- list options
def _subparsers():
    import argparse

    from colmap_miho.cli import build_parser

    (sub,) = [a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction)]
    return sub.choices


def _list_options():
    """(command, option, action) of every option that takes several values."""
    return [(name, action.option_strings[-1], action) for name, p in _subparsers().items()
            for action in p._actions
            if action.nargs in ("+", "*") or (isinstance(action.nargs, int) and action.nargs > 1)]


def test_every_list_option_takes_commas_and_spaces():
    from colmap_miho.commands._options import ListAction

    found = _list_options()
    assert {opt for _, opt, _ in found} >= {"--auc-thresholds", "--camera-params"}
    for name, opt, action in found:
        assert isinstance(action, ListAction), f"{name} {opt} does not take a,b,c"
    # --camera-params: a string option of COLMAP's text, a list option like the others
    for name, p in _subparsers().items():
        for action in p._actions:
            if "--camera-params" in action.option_strings:
                assert isinstance(action, ListAction), name


def _parse(argv):
    from colmap_miho.cli import build_parser

    return build_parser().parse_args(argv)


def test_list_values_read_the_same_with_commas_spaces_or_both():
    base = ["report", "--model", "m"]
    forms = (["0.5,1,5"], ["0.5", "1", "5"], ["0.5,1", "5"], ["0.5,", "1,5"])
    for form in forms:
        assert _parse([*base, "--auc-thresholds", *form]).auc_thresholds == [0.5, 1.0, 5.0], form
    cmd = ["map", "--database", "d", "--images", "i", "--output", "o", "--camera-model", "PINHOLE"]
    for form in (["500,501,320,240"], ["500", "501", "320", "240"], ["500,501", "320,240"]):
        assert _parse([*cmd, "--camera-params", *form]).camera_params == "500,501,320,240", form
    run = ["run", "--images", "i", "--output", "o", "--camera-params", "500", "320", "240", "-0.01"]
    assert _parse(run).extract_camera_params == "500,320,240,-0.01"  # a negative distortion term


def test_bad_list_values_are_one_line_errors(capsys):
    import pytest

    for bad in (["0.5,x"], [","]):
        with pytest.raises(SystemExit) as exc:
            _parse(["report", "--model", "m", "--auc-thresholds", *bad])
        assert exc.value.code == 2
        err = capsys.readouterr().err
        assert "--auc-thresholds" in err.splitlines()[-1]


def test_every_recipe_option_names_the_default_recipe():
    """``--recipe``'s help on every command that takes one says which recipe runs without it."""
    from colmap_miho.recipe import DEFAULT_RECIPE

    commands = set()
    for name, p in _subparsers().items():
        for action in p._actions:
            if "--recipe" in action.option_strings:
                commands.add(name)
                assert action.default is None, name  # None: load_recipe's default, one place
                assert f"default {DEFAULT_RECIPE}" in (action.help or ""), (name, action.help)
    assert commands >= {"refine", "run", "compare", "demo", "map"}
