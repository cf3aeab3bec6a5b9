"""Test runner: ``python kill_after_saves.py KIND N CLI_ARGS...`` runs ``colmap-miho CLI_ARGS``
with one pair per filter chunk and an image budget of two images (several track groups, see
``small_budget``), and SIGKILLs its own process right after the run store has
saved its N-th item of KIND ("filter": filter chunks, "group": refine track groups):
``test_resume`` then resumes the run and compares it with an uninterrupted one."""

import os
import signal
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))  # this checkout's colmap_miho

from small_budget import SMALL_WORKER_MATCHES, two_images  # noqa: E402

import colmap_miho.pipeline.filter as filter_stage  # noqa: E402
import colmap_miho.pipeline.track_groups as track_groups  # noqa: E402
from colmap_miho.cli import main  # noqa: E402
from colmap_miho.pipeline.store import RunStore  # noqa: E402
from colmap_miho.pipeline_config import PipelineConfig  # noqa: E402

SAVERS = {"filter": "save_filter_chunk", "group": "save_group"}


def kill_after(kind: str, n: int) -> None:
    """Wrap the store's saver of ``kind`` so that the process dies by SIGKILL after ``n`` saves."""
    name = SAVERS[kind]
    save = getattr(RunStore, name)
    calls = 0

    def wrapped(self, *args, **kwargs):
        nonlocal calls
        save(self, *args, **kwargs)
        calls += 1
        if calls == n:
            os.kill(os.getpid(), signal.SIGKILL)

    setattr(RunStore, name, wrapped)


if __name__ == "__main__":
    filter_stage.MAX_CHUNK_MATCHES = 1  # one pair per chunk: several chunks on a small scene
    PipelineConfig.image_budget_bytes = two_images  # type: ignore[method-assign]
    track_groups.MIN_MATCHES_PER_REFINE_WORKER = SMALL_WORKER_MATCHES  # several groups on a small scene
    track_groups.MIN_MATCHES_TO_START_WORKERS = 0
    kill_after(sys.argv[1], int(sys.argv[2]))
    sys.exit(main(sys.argv[3:]))
