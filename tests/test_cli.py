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
