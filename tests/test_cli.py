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
