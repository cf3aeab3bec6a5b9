"""``colmap-miho report``: reconstruction statistics and pose accuracy against ground truth."""

from __future__ import annotations

from pathlib import Path

from ._options import add_auc_arguments

HELP = ("reconstruction statistics; with --gt pose AUC/mAA, and two-view pose AUC and keypoint accuracy "
        "of --database")
DESCRIPTION = (
    "Print reconstruction statistics of a COLMAP model. With --gt (COLMAP model folder, text or "
    "binary, images matched by name): relative-pose AUC at --auc-thresholds (default "
    "0.5/1/2/5/10/20 deg) and mAA over all GT pairs, and "
    "rotation / camera-centre errors after a similarity alignment. With --database too: the "
    "paper's two-view pose AUCs (E and F protocols) from the database's verified matches, on the "
    "dataset's pairs_with_gt.txt when the GT folder has one (else all GT pairs), and the keypoint "
    "accuracy of its inlier matches under the GT geometry (distance to the GT epipolar lines; "
    "residuals of the tracks triangulated with the GT cameras, wrong tracks apart). --model is "
    "optional when --gt and --database are given. The database is read through a copy and never "
    "changed."
)
ORDER = 40


def add_arguments(parser) -> None:
    parser.add_argument("--model", type=Path, default=None,
                        help="COLMAP model folder (text or binary); optional with --gt and --database")
    parser.add_argument("--database", type=Path, default=None,
                        help="COLMAP database for the two-view pose AUCs and the keypoint accuracy")
    parser.add_argument("--gt", type=Path, default=None,
                        help="GT COLMAP model folder (or a dataset folder with gt_model/)")
    parser.add_argument("--pairs", type=Path, default=None,
                        help="pairs file (name1 name2 ...) for the two-view AUCs")
    parser.add_argument("--seed", type=int, default=0, help="RANSAC seed of the two-view protocols")
    add_auc_arguments(parser)
    parser.add_argument("--json", type=Path, default=None, help="write the full report as JSON")
    parser.add_argument("--html", type=Path, default=None,
                        help="also write a self-contained HTML page (table, pose-error curves with --gt, a 3D view "
                             "of the model) to open in a browser (needs the plots extra)")
    parser.add_argument("--ply", type=Path, default=None,
                        help="also export the model's 3D points (with colours) as PLY")


def paths(args) -> tuple[dict, dict]:
    """Inputs and outputs for the CLI's overlap check."""
    from ..adapters.paths import model_input_files

    if args.pairs is not None and not args.pairs.is_file():
        raise FileNotFoundError(f"--pairs not found: {args.pairs}")
    inputs = {"--model": args.model, "--database": args.database, "--gt": args.gt, "--pairs": args.pairs,
              **model_input_files(args.model, "--model"), **model_input_files(args.gt, "--gt")}
    return inputs, {"--json": args.json, "--ply": args.ply, "--html": args.html}


def run(args) -> int:
    from ..errors import UserError
    from ..reporting.report import build_report, write_report_json
    from ..reporting.report_text import format_report
    from ._options import auc_thresholds

    if args.model is None:
        if args.gt is None or args.database is None:
            raise UserError("give --model, or --gt and --database (keypoint accuracy without a model)")
        if args.ply:
            raise UserError("--ply needs --model")
    elif not args.model.exists():
        raise FileNotFoundError(f"--model not found: {args.model}")
    thresholds = auc_thresholds(args)
    report = build_report(args.model, database=args.database, gt=args.gt, pairs=args.pairs, seed=args.seed,
                          thresholds=thresholds)
    if not args.quiet:
        print(format_report(report))
    if args.ply:
        from ..reporting.gt_model import load_reconstruction
        from ..reporting.pointcloud import export_ply

        args.ply.parent.mkdir(parents=True, exist_ok=True)
        export_ply(load_reconstruction(args.model), args.ply)
        if not args.quiet:
            print(f"points written to {args.ply}")
    if args.html:
        from ..reporting.html_report import write_model_html

        args.html.parent.mkdir(parents=True, exist_ok=True)
        if write_model_html(args.html, report, args.model) is not None and not args.quiet:
            print(f"page written to {args.html}")
    if args.json:
        write_report_json(report, args.json)
        if not args.quiet:
            print(f"report written to {args.json}")
    return 0
