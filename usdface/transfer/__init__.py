"""Implant personalized capture shapes into an avatar (Menzel et al. 2022, sec. 3.3): registration
(:mod:`.register`), correspondence (:mod:`.correspond`), automatic retargeting eq. (4) (:mod:`.retarget`),
seamless partial deformation transfer (:mod:`.partial_dt`), eyelid repair (:mod:`.eyelids`), and the
end-to-end :func:`personalize_avatar` (:mod:`.pipeline`).
"""

from __future__ import annotations

from .pipeline import PersonalizeResult, personalize_avatar
from .retarget import retarget_weights

__all__ = ["personalize_avatar", "PersonalizeResult", "retarget_weights"]
