"""A refine-stage image budget of two synthetic-scene images, so that the small test scenes'
tracks are cut into several groups (``PipelineConfig.image_budget_bytes`` replaced by it)."""

#: Bytes of two 640 x 480 float32 images (the synthetic scenes' size), and a little more.
TWO_IMAGES_BYTES = 2 * 640 * 480 * 4 + 1000


def two_images(self, slots: int) -> int:
    """Stands in for :meth:`PipelineConfig.image_budget_bytes`."""
    return TWO_IMAGES_BYTES


#: ``track_groups.MIN_MATCHES_PER_REFINE_WORKER`` on the small test scenes (it sets the groups' match
#: bound), so that their tracks make several groups.
SMALL_WORKER_MATCHES = 20
