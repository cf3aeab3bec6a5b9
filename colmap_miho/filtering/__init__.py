"""MOP / MOP+MiHo match filtering (paper Sec. 3.1-3.2, App. A-D); the entry point is :func:`.api.filter_matches`."""
