"""The NCC search of one match: template shapes, correlation maps, search and sub-pixel step."""
