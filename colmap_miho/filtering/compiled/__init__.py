"""The filter's compiled (numba) kernels, one module per numpy module they accelerate
(:mod:`.homography` holds the per-hypothesis helpers that :mod:`.scoring` and :mod:`.ransac`
share). Each kernel module's jitted kernels are its :data:`KERNELS` handle
(:class:`colmap_miho.compiled.Kernels`), built on the first call; :func:`..preload.warm` loads
them all ahead. These modules import nothing else of the filter: the filter's modules import
them. The numpy functions stay the reference (and the path of the torch scoring on CUDA); the
tests check each kernel against them."""
