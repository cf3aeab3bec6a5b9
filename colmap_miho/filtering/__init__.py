"""MOP / MOP+MiHo match filtering (paper Sec. 3.1-3.2, App. A-D).

Modules, in data-flow order:

- ``config``: :class:`FilterConfig` (paper parameters and the speed options).
- ``miho``: the RANSAC problem of MOP or MiHo, the 90-degree rotation fix, VSAC square root.
- ``problem``: :class:`~.problem.Problem` (the point sets a hypothesis is fitted to) and
  :class:`~.problem.Hypotheses` (a stack of them).
- ``sampling``: minimal samples (uniform or local draws, spread test, local candidates) and
  the adaptive iteration bound.
- ``scoring``: the heavy kernels in numpy (closed-form minimal solver, singular-value test,
  exact one-way pre-scoring, full errors and inlier masks).
- ``ransac``: one batched RANSAC run (the round loop: batches, full scoring in bound order,
  top-z buffer, adaptive stopping, refit).
- ``mop``: the outer loop (adaptive threshold, failure counter).
- ``assign``: homography assignment of the kept matches (App. A.4).
- ``api``: :func:`filter_matches` and :class:`FilterResult`.
- ``homography``: batched homography maths used by all of the above (numpy or torch).
- ``torch_scoring``: the ``device`` argument, and the RANSAC kernels in torch on that device.
"""
