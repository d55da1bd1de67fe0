"""The sweep solver (Langer, Breton & Zucker): discrete ordinates on the lattice.

``_solver.py`` (the light solve) → ``_kernel.py`` (one face sweep) with ``_uncollided.py``
(first-collision sun and sky), ``_terms.py`` (which terms a scene needs), ``_krylov.py``
(GMRES) and ``_implicit.py`` (gradients of the fixed point); ``_march.py`` (camera rays
through the solved lattice); ``_model.py`` (the forward model)."""
