"""The filter's compiled (numba) kernels, one module per numpy module they accelerate
(:mod:`.scoring` also holds the batch scoring and refit of :mod:`..ransac`, which share its
helpers: no kernel calls a jitted function of another file, whose changes numba's cache would
not notice). Each kernel module's jitted kernels are its :data:`KERNELS` handle
(:class:`colmap_miho.compiled.Kernels`), built on the first call; :func:`..preload.warm` loads
them all ahead. These modules import nothing else of the filter: the filter's modules import
them. The numpy functions stay the reference (and the path of the torch scoring on CUDA); the
tests check each kernel against them."""
