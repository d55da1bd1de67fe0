"""The scene description: what a scene file (schema v1, ``data/scenes/SCHEMA.md``) says,
validated, and the differentiable parameters named by dotted paths."""
