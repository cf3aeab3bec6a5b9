"""``colmap-miho demo``: the whole job on a built-in scene with exact ground truth."""

from __future__ import annotations

from pathlib import Path

from ..errors import InvalidInput
from ._options import add_recipe_arguments, load_run_recipe, quiet_colmap

HELP = "run the whole job on a built-in scene with exact ground truth (no downloads)"
DESCRIPTION = (
    "Render a small piecewise-planar scene (walls, floor, a poster and a box textured with "
    "scikit-image's bundled photographs) from known cameras, then extract and match SIFT, "
    "refine, map and compare with the unrefined baseline against the exact ground truth. "
    "Prints where the table and plots are."
)
ORDER = 1


def add_arguments(parser) -> None:
    parser.add_argument("--output", type=Path, default=Path("colmap_miho_demo"),
                        help="work folder (default ./colmap_miho_demo)")
    parser.add_argument("--num-images", type=int, default=8, help="rendered views (default 8)")
    parser.add_argument("--size", default="640x480", help="image size WxH (default 640x480)")
    parser.add_argument("--max-features", type=int, default=None,
                        help="SIFT features per image (default 2048; 1024 with --quick)")
    parser.add_argument("--quick", action="store_true", help="6 views at 480x360 and 1024 features (for tests)")
    add_recipe_arguments(parser)


def _size(text: str) -> tuple[int, int]:
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise InvalidInput(f"--size must look like 640x480, got {text!r}") from None
    return w, h


def run(args) -> int:
    import time

    from ..adapters.paths import refuse_links_below
    from ..extras import require
    from ..kernel_cache import compile_in_background, families_for
    from ..pipeline.jobs import ExtractionOptions, JobOptions, run_from_images
    from ..reporting.compare import format_comparison
    from ..reporting.demo_scene import make_demo_scene

    for module, purpose in (("skimage", "the demo scene"), ("matplotlib", "the demo's figures")):
        require(module, "demo", purpose)
    recipe = load_run_recipe(args)
    w, h = _size(args.size)
    compile_in_background(families_for(recipe))  # while the scene renders and its features are matched
    n = args.num_images
    max_features = args.max_features or (1024 if args.quick else 2048)
    if args.quick:
        n, w, h = 6, 480, 360
    t0 = time.perf_counter()
    scene_dir = args.output / "scene"
    refuse_links_below(args.output, {"--output (scene/images)": scene_dir / "images" / "x",
                                     "--output (scene/gt_model)": scene_dir / "gt_model" / "x"})
    scene = make_demo_scene(args.output / "scene", num_images=n, width=w, height=h, seed=args.seed)
    quiet_colmap(args.verbose)
    out = run_from_images(
        scene.image_dir, args.output, gt=scene.gt_dir, recipe=recipe, compare=True,
        extraction=ExtractionOptions(max_features=max_features),
        options=JobOptions(seed=args.seed, workers=args.workers, device=args.device, progress=not args.quiet,
                           verbose=args.verbose),
    )
    if not args.quiet:
        print(format_comparison(out["result"]))
        print(f"scene:  {scene.image_dir} (exact GT model: {scene.gt_dir})")
        print(f"done in {time.perf_counter() - t0:.0f} s")
    return 0
