"""Personalized ARKit blendshapes on the capture mesh (Menzel, Botsch & Latoschik, VRST 2022, sec. 3.2).

:func:`fit_personalized_shapes` turns a :class:`usdface.model.Capture` (neutral scan B0, training scans S_i
with the phone's weights w_ij, generic template rig on the same topology) into a :class:`FitResult` whose
``rig`` is the person's blendshape rig on the capture mesh. Methods:

* ``"dt"``        - deformation transfer of the template onto B0 (Sumner & Popović 2004), :mod:`.dt`;
* ``"ebfr"``      - example-based facial rigging's blendshape optimisation (Li, Weise & Pauly
                    2010), :mod:`.ebfr`;
* ``"menzel"``    - the position fit, eqs. (1)-(3) (default), :mod:`.fit`, regularisation by
                    cross-validation :mod:`.crossval`;
* ``"laplacian"`` - the position fit plus Hable's Laplacian term and region masks, :mod:`.laplacian`.

Pure numpy/scipy: no USD in here. :func:`evaluate_rig` scores a rig on test frames (eq. 5).
"""

from __future__ import annotations

from .api import METHODS, FitResult, fit_personalized_shapes
from .dt import PoissonSolver, deformation_transfer, eyelid_triangles
from .evaluate import evaluate_rig, truth_error

__all__ = ["fit_personalized_shapes", "FitResult", "METHODS", "deformation_transfer", "PoissonSolver",
           "eyelid_triangles", "evaluate_rig", "truth_error"]
