"""The splat solver (Zhang & Crawfis): sheet-based splatting, one pass per camera.

``_sheets.py`` (host set-up of one camera's sheets) → ``_pass.py`` (the traced pass) →
``_model.py`` (the forward model)."""
