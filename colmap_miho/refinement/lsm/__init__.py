"""Least-squares matching: the alignment's result and bounds, the torch alignment (the
reference), its compiled kernel, and the step of the NCC refinement that runs them."""
