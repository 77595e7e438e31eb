"""File formats: the only package that knows USD, OBJ, JSON and CSV. Importing it registers usdface's USD
schemas (:func:`usdface.schemas.register`), which must happen before the first USD stage is created."""

from .. import schemas as _schemas

_schemas.register()
