"""The NCC search of one match: template shapes, batched correlation maps, the search of one
direction, the iterated sub-pixel step and their compiled kernel."""
