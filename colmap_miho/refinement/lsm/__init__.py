"""Least-squares matching: the alignment (torch reference and compiled kernel) and its step."""
