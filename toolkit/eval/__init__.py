"""Pure metric functions (no plotting, no CLI): trajectory, relations, depth, geometry, image."""
