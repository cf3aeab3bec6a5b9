"""Outputs written inside output folders never land on files read inside input folders.

``compare`` / ``run`` write model files in ``OUTPUT/<side>/model``: a ground truth kept there
must be refused before any work, with one line, and stay byte-identical.
"""

from __future__ import annotations

import hashlib
import shutil
from pathlib import Path

import pytest

from colmap_miho.adapters.paths import check_distinct, comparison_paths, folder_files, model_input_files
from colmap_miho.cli import main
from colmap_miho.errors import UserError


def digests(folder: Path) -> dict[str, str]:
    return {p.name: hashlib.sha256(p.read_bytes()).hexdigest() for p in sorted(folder.iterdir()) if p.is_file()}


def error_lines(err: str) -> list[str]:
    return [line for line in err.splitlines() if line.strip()]


def _text_gt(scene, folder: Path) -> Path:
    folder.mkdir(parents=True)
    scene.gt_reconstruction.write_text(str(folder))
    return folder


@pytest.mark.parametrize("case", ["compare_baseline", "compare_refined", "compare_repeat_run", "run_gt",
                                  "run_compare_gt", "compare_dataset_folder"])
def test_gt_inside_the_output_is_refused_before_work(case, db_copy, scene, tmp_path, capfd):
    """The attack's repro: ``--gt w/baseline/model`` with ``--output w``. Exit 2, one line that
    names the output file and the GT, the GT untouched, nothing mapped."""
    work = tmp_path / "w"
    sub = {"compare_baseline": "baseline/model", "compare_refined": "refined/model",
           "compare_repeat_run": "refined/runs/seed1/model", "run_gt": "refined/model",
           "run_compare_gt": "baseline/model", "compare_dataset_folder": "baseline/model/gt_model"}[case]
    gt = _text_gt(scene, work / sub)
    gt_arg = gt.parent if case == "compare_dataset_folder" else gt
    before = digests(gt)
    if case.startswith("compare"):
        argv = ["compare", "--database", str(db_copy), "--images", str(scene.image_dir), "--output", str(work),
                "--gt", str(gt_arg), "--repeats", "2" if case == "compare_repeat_run" else "1"]
    else:
        argv = ["run", "--images", str(scene.image_dir), "--output", str(work), "--gt", str(gt_arg),
                *(["--compare"] if case == "run_compare_gt" else [])]
    capfd.readouterr()
    assert main([*argv, "-q"]) == 2
    lines = error_lines(capfd.readouterr().err)
    assert len(lines) == 1, lines
    assert "--gt" in lines[0] and ("holds a COLMAP text model" in lines[0] or "same file" in lines[0]), lines
    assert digests(gt) == before
    assert not (work / "database.db").exists() and not (work / "refined" / "database.db").exists()


def test_binary_gt_inside_the_output_is_refused(db_copy, scene, tmp_path, capfd):
    """A binary GT where the baseline model goes: the same-file rule (no text model to spot)."""
    gt = tmp_path / "w" / "baseline" / "model"
    gt.mkdir(parents=True)
    scene.gt_reconstruction.write(str(gt))
    before = digests(gt)
    capfd.readouterr()
    assert main(["compare", "--database", str(db_copy), "--images", str(scene.image_dir), "--output",
                 str(tmp_path / "w"), "--gt", str(gt), "-q"]) == 2
    lines = error_lines(capfd.readouterr().err)
    assert len(lines) == 1 and "is the same file as --gt" in lines[0] and "cameras.bin" in lines[0], lines
    assert digests(gt) == before


def test_job_runners_check_their_own_paths(db_copy, scene, tmp_path):
    """The Python API refuses the same overlap (no CLI in front of it)."""
    from colmap_miho.pipeline.jobs import compare_databases, run_from_images

    gt = tmp_path / "w" / "refined" / "model"
    gt.mkdir(parents=True)
    scene.gt_reconstruction.write(str(gt))
    before = digests(gt)
    with pytest.raises(UserError, match="same file as --gt"):
        compare_databases(db_copy, scene.image_dir, tmp_path / "w", gt=gt)
    with pytest.raises(UserError, match="same file as --gt"):
        run_from_images(scene.image_dir, tmp_path / "w", gt=gt)
    assert digests(gt) == before and not (tmp_path / "w" / "database.db").exists()


def test_map_into_a_text_model_is_refused(db_copy, scene, tmp_path, capfd):
    model = _text_gt(scene, tmp_path / "model")
    before = digests(model)
    capfd.readouterr()
    assert main(["map", "--database", str(db_copy), "--images", str(scene.image_dir), "--output", str(model),
                 "-q"]) == 2
    lines = error_lines(capfd.readouterr().err)
    assert len(lines) == 1 and f"--output {model} holds a COLMAP text model" in lines[0], lines
    assert digests(model) == before


def test_an_output_on_an_image_is_refused(db_copy, scene, tmp_path, capfd):
    """Files inside --images are inputs: ``map --json`` onto an image is refused."""
    image = sorted(scene.image_dir.iterdir())[0]
    before = image.read_bytes()
    capfd.readouterr()
    assert main(["map", "--database", str(db_copy), "--images", str(scene.image_dir), "--output",
                 str(tmp_path / "m"), "--json", str(image), "-q"]) == 2
    lines = error_lines(capfd.readouterr().err)
    assert len(lines) == 1 and f"is the same file as --images ({image.name})" in lines[0], lines
    assert image.read_bytes() == before


@pytest.mark.parametrize("where", ["images", "images/model"])
def test_an_output_folder_among_the_images_is_refused(db_copy, scene, tmp_path, capfd, where):
    """``map --output`` (and ``run`` / ``compare``'s) equal to --images, or inside it, would
    write the model among the images: refused, nothing written."""
    images = tmp_path / "images"
    shutil.copytree(scene.image_dir, images)
    before = sorted(p.name for p in images.rglob("*"))
    capfd.readouterr()
    assert main(["map", "--database", str(db_copy), "--images", str(images), "--output", str(tmp_path / where),
                 "-q"]) == 2
    lines = error_lines(capfd.readouterr().err)
    assert len(lines) == 1 and "--images" in lines[0] and "among the input files" in lines[0], lines
    assert sorted(p.name for p in images.rglob("*")) == before
    with pytest.raises(UserError, match="among the input files"):
        comparison_paths(tmp_path / where, images=images)


def test_comparison_paths_lists_every_file_written(tmp_path):
    ins, outs = comparison_paths(tmp_path / "w", images=tmp_path / "images", gt=tmp_path / "gt", repeats=3, seed=5)
    written = {str(p.relative_to(tmp_path / "w")) for p in outs.values()}
    for name in ("baseline/model/cameras.bin", "refined/model/points3D.txt", "refined/runs/seed7/model/images.bin",
                 "baseline/runs/seed6/model/frames.bin", "compare.json", "refined/refine.json",
                 "plots/points_refined.png", "baseline/points.ply"):
        assert name in written, name
    assert "refined/runs/seed8/model/images.bin" not in written
    assert ins["--gt/gt_model (images.txt)"] == tmp_path / "gt" / "gt_model" / "images.txt"
    _, outs = comparison_paths(tmp_path / "r", images=tmp_path / "images", compare=False)
    assert {str(p.relative_to(tmp_path / "r")) for p in outs.values()} >= {"database.db", "report.json",
                                                                          "refined/model/cameras.bin"}


def test_check_distinct_on_input_folder_files(tmp_path):
    images = tmp_path / "images"
    (images / "sub").mkdir(parents=True)
    (images / "sub" / "a.png").write_bytes(b"png")
    (images / ".hidden").mkdir()
    (images / ".hidden" / "x").write_bytes(b"x")
    files = folder_files(images, "--images")
    assert list(files) == ["--images (sub/a.png)"]
    with pytest.raises(UserError, match=r"--json .* is the same file as --images \(sub/a.png\)"):
        check_distinct(files, {"--json": images / "sub" / ".." / "sub" / "a.png"})
    check_distinct({**files, **model_input_files(tmp_path / "gt", "--gt")}, {"--json": images / "b.json"})
