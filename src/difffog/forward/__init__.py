"""Forward models: parameters → light → images.  One abstract interface (``_model.py``), the
sweep and the splat side by side (``sweep/``, ``splat/``), shared camera code
(``_camera.py``) and the registry that builds either by name (``_registry.py``)."""
