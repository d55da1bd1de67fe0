"""Fitting: unknowns (``_unknowns.py``) → targets (``_targets.py``) → residuals and their
Jacobian (``_residuals.py``) → the optimizer stepped from Python (``_stepper.py``) by the
driver shared by ``fit`` and ``fit_batch`` (``_driver.py``), with checkpoints
(``_checkpoint.py``) → the result and its statistics (``_result.py``)."""
