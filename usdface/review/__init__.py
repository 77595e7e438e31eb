"""``usdface review``: a self-contained web page of a personalize result (:mod:`usdface.review.page` builds
it from arrays, :mod:`usdface.review.collect` reads them from the layer, its capture and a take)."""

from .page import ReviewData, ReviewMesh, Sequence, build_review_html

__all__ = ["ReviewData", "ReviewMesh", "Sequence", "build_review_html"]
