"""The filter's compiled (numba) kernels, one module per numpy module they accelerate; no kernel
calls a jitted function of another file (numba's cache would miss its changes). The numpy functions
stay the reference the tests check them against."""
