"""Pyblish plugins: validate an ARKit face rig and personalize it at publish time.

Needs ``pyblish-base`` (``pip install 'usdface[pipeline]'``). The plugins act on instances of the family
``usdface.avatar`` whose data holds ``avatar`` (USD file), ``capture`` (capture folder or capture USD) and
``output`` (the layer to write), plus optional ``usdfaceOptions`` (personalize options such as ``method``),
``force`` and ``inspect``. A studio's own collector usually creates them; :class:`CollectUsdFaceItems`
makes them from ``context.data["usdfaceItems"]`` (a list of dicts) or ``context.data["usdfaceManifest"]``
(a batch manifest, see :mod:`usdface.pipeline.batch`).

* :class:`ValidateUsdFaceRig` (validator): usdface's face-rig rules + OpenUSD's validators on the avatar; any
  error fails the publish (Pyblish then skips extraction); warnings are logged; the report is stored in
  ``instance.data["usdfaceCheck"]``.
* :class:`ValidateUsdFaceCapture` (validator): the capture reads (names, topology, weights).
* :class:`ValidateUsdFaceOptions` (validator): ``usdfaceOptions`` are personalize's, with accepted values.
* :class:`ValidateUsdFaceOutputs` (validator): the layer and (with ``review``) the review page can be
  written there (not an input, not an existing file without ``force``, a place that takes them), so a
  publish fails before any file is written.
* :class:`ExtractUsdFacePersonalized` (extractor): runs ``personalize``, re-checks the written layer, and
  records it in ``instance.data["files"]`` and ``instance.data["representations"]`` (the OpenPype/AYON shape).
  A layer that fails the re-check is set aside as ``<layer>.failed`` (as ``usdface batch`` sets aside a
  failed item's output), to look at with ``usdface check``; the error says so.
* :class:`ExtractUsdFaceReview` (extractor, with ``instance.data["review"]``): the self-contained review page
  (``usdface review``) beside the layer, attached as a ``review`` representation. When it fails, the layer
  this publish wrote is removed (all or nothing, as the API's several outputs) and taken off the instance's
  files and representations; one that replaced an earlier layer (``force``) is left, and the error says so.

Example::

    import pyblish.api, pyblish.util
    from usdface.pipeline import pyblish_plugins
    pyblish_plugins.register()
    context = pyblish.api.Context()
    context.data["usdfaceItems"] = [{"avatar": "a.usdc", "capture": "capture/", "output": "a_person.usda"}]
    pyblish.util.publish(context)
"""

from __future__ import annotations

import contextlib
import logging
import os
import warnings
from pathlib import Path

from ..errors import add_to_message

try:
    import pyblish.api as _pyblish
except ImportError as exc:  # pragma: no cover - exercised only without the optional extra
    raise ImportError("usdface's Pyblish plugins need pyblish-base: pip install 'usdface[pipeline]'") from exc

FAMILY = "usdface.avatar"


@contextlib.contextmanager
def _warnings_to_log(plugin, instance, report_warnings=None):
    """The Python warnings usdface gives while ``plugin`` runs (a capture's repeated frames, the shapes the
    capture barely shows, ...) go to the plugin's log, which a publish UI shows, and to
    ``instance.data["usdfaceWarnings"]``; they went to stderr only, outside the publish's records. The
    host's filters stay (``-W error`` still fails); usdface's own are shown every time. Yields a list to
    which the caller may add report notes (a personalize result's ``report["warnings"]``)."""
    notes = [] if report_warnings is None else report_warnings
    with warnings.catch_warnings(record=True) as caught:
        warnings.filterwarnings("always", module=r"usdface(\.|$)")
        try:
            yield notes
        finally:
            said = instance.data.setdefault("usdfaceWarnings", [])
            for text in dict.fromkeys([str(w.message) for w in caught] + [str(n) for n in notes]):
                if text not in said:
                    said.append(text)
                    plugin.log.warning(text)


def _personalize_options(instance) -> dict:
    """The options the layer's extractor gives ``personalize``: ``usdfaceOptions`` (a manifest's columns)
    first, then the instance data's ``inspect`` and ``take``, and ``force`` true when either gives it true -
    the ``force`` and take the review page and the outputs' validator go by too."""
    data = instance.data
    options = dict(data.get("usdfaceOptions") or {})
    # True or False (None: the default), as personalize's own options: instance data force="no" (or a
    # manifest cell 'no') counted as true and replaced an existing layer. Either one true replaces (as
    # 'usdface batch --force' redoes a row whose force column is false: docs/pipeline.md); each given is
    # checked. The options' false beat the data's true until stop 53
    given = [_flag(instance, "force", options) if "force" in options else False,
             _flag(instance, "force") if "force" in data else False]
    options["force"] = any(given)
    inspect = _chosen_flag(instance, "inspect", options)
    if inspect is not None:                             # (absent from both: personalize's default)
        options["inspect"] = inspect
    if data.get("take") and not options.get("take"):   # as 'personalize --take': it plays in the layer as
        options["take"] = data["take"]                  # on the review page
    return options


def _chosen_flag(instance, name: str, options: dict) -> bool | None:
    """The boolean ``name`` a publish uses, checked where it is taken from (:func:`_flag`): ``options``' (the
    instance's ``usdfaceOptions``) when they give it, else the instance data's, else None (neither gives
    it). The one used is the one checked: the data's was checked even when ``usdfaceOptions`` gave its own,
    and a word there failed a publish that never used it (stop 51's review). ``inspect``'s rule; ``force``
    is true when either gives it true (stop 53)."""
    if name in options:
        return _flag(instance, name, options)
    if name in instance.data:
        return _flag(instance, name)
    return None


def _flag(instance, name: str, options: dict | None = None) -> bool:
    """The boolean ``name`` of ``instance``'s data (or of ``options``, its ``usdfaceOptions``): ``True`` or
    ``False`` (``None``: False), anything else refused naming the instance
    (:func:`usdface.errors.expect_flag`, the one check of a boolean option): ``force``, ``inspect`` and
    ``review`` given as ``"no"`` counted as true, so a publish replaced an existing layer or wrote a review
    page it was told not to."""
    from ..errors import expect_flag

    where = "usdfaceOptions" if options is not None else "data"
    value = (options if options is not None else instance.data).get(name)
    return expect_flag(value, name, f"instance {instance}'s", False,
                       fix=f"set the instance's {where} {name}=True or {name}=False (a manifest's {name} "
                           "column: true or false)")


def _default_personalize() -> bool:
    """Whether every registered layer extractor runs the built-in ``personalize`` (a studio's own step takes
    its own options and decides where it writes: the validators of those leave it alone)."""
    extractors = [ExtractUsdFacePersonalized, *(p for p in _pyblish.registered_plugins()
                                                if issubclass(p, ExtractUsdFacePersonalized))]
    return all(p.personalize is ExtractUsdFacePersonalized.default_personalize for p in extractors)


def _refuse_malformed_items(items) -> None:
    """Every item of ``context.data["usdfaceItems"]`` a mapping with a non-empty ``avatar``, ``capture`` and
    ``output``, checked before any instance is made: a misspelt key (``"out"``) failed the collector with a
    bare ``KeyError: 'output'``, a path given instead of a dict with ``TypeError: string indices ...``."""
    from collections.abc import Mapping

    from ..errors import InputFileError

    example = '{"avatar": "hero.usdc", "capture": "captures/anna/", "output": "hero_anna.usda"}'
    for i, item in enumerate(items):
        where = f'context.data["usdfaceItems"][{i}]'
        if not isinstance(item, Mapping):
            raise InputFileError(f"{where} is a {type(item).__name__} ({item!r:.60}), not a dict",
                                 fix=f"give each item as a dict, {example}")
        missing = [k for k in ("avatar", "capture", "output") if not item.get(k)]
        if missing:
            has = ", ".join(map(str, item)) or "no keys"
            raise InputFileError(f"{where} lacks {', '.join(missing)} (has {has})",
                                 fix=f"give every item an avatar, a capture and an output, {example}")


class CollectUsdFaceItems(_pyblish.ContextPlugin):
    """One ``usdface.avatar`` instance per item of ``context.data["usdfaceItems"]`` or of the batch manifest
    ``context.data["usdfaceManifest"]``."""

    order = _pyblish.CollectorOrder
    label = "Collect usdface avatars"

    def process(self, context):
        items = list(context.data.get("usdfaceItems") or [])
        manifest = context.data.get("usdfaceManifest")
        if manifest:
            from .batch import read_manifest

            for i in read_manifest(manifest):
                options = dict(i.options)
                # 'review' is the publish's (ExtractUsdFaceReview), not personalize's: a manifest column
                # 'review' failed ValidateUsdFaceOptions as an unknown personalize option
                review = {"review": options.pop("review")} if "review" in options else {}
                items.append(dict(avatar=i.avatar, capture=i.capture, output=i.output, **review,
                                  usdfaceOptions=options))
        _refuse_malformed_items(items)
        for item in items:
            name = Path(item["output"]).stem
            instance = context.create_instance(name, family=FAMILY)
            instance.data.update(item)
            instance.data.setdefault("usdfaceOptions", {})
            self.log.info("collected %s: %s + %s -> %s", name, item["avatar"], item["capture"],
                          item["output"])


class ValidateUsdFaceRig(_pyblish.InstancePlugin):
    """The avatar passes usdface's face-rig rules and OpenUSD's validators (errors fail the publish)."""

    order = _pyblish.ValidatorOrder
    families = [FAMILY]
    label = "Validate face rig (usdface check)"
    #: Also run OpenUSD's own validators.
    pixar = True
    #: Warnings fail the publish too.
    strict = False

    def process(self, instance):
        from ..api import check

        # the studio's control names read as ARKit's, as personalize will (usdfaceOptions' name_map); the
        # face mesh personalize will take (a shot with two characters fails here without one, not in the
        # extractor)
        options = instance.data.get("usdfaceOptions") or {}
        name_map, face_mesh = options.get("name_map"), options.get("face_mesh")
        issues = check(instance.data["avatar"], pixar=self.pixar, name_map=name_map, face_mesh=face_mesh)
        instance.data["usdfaceCheck"] = [i.to_dict() for i in issues]
        if _default_personalize():
            # an already personalized avatar (a usdface layer, its flattened export) passes the rules; it
            # failed only in the extractor, after other instances' extractors had run
            from ..io.usd_rig import refuse_usdface_output

            refuse_usdface_output(instance.data["avatar"])
        for issue in issues:
            if issue.severity == "warning":
                self.log.warning(str(issue))
            elif issue.severity == "info":
                self.log.info(str(issue))
        bad = [i for i in issues if i.severity == "error" or (self.strict and i.severity == "warning")]
        if bad:
            from ..errors import RigError

            more = f"; ... {len(bad) - 5} more" if len(bad) > 5 else ""
            lines = "; ".join(f"{i.severity.upper()} [{i.rule}] {i.prim}: {i.message}"
                              for i in bad[:5]) + more
            first = next((i.fix for i in bad if i.fix), "")
            raise RigError(f"{len(bad)} face-rig problem(s): {lines}", path=instance.data["avatar"],
                           fix=(first + "; " if first else "") + "run 'usdface check' on the avatar for the "
                           "whole list" + (" (with --name-map)" if name_map else ""))


class ValidateUsdFaceCapture(_pyblish.InstancePlugin):
    """The capture reads: neutral, template and frames with consistent topology and ARKit weights."""

    order = _pyblish.ValidatorOrder
    families = [FAMILY]
    label = "Validate capture (usdface)"

    def process(self, instance):
        from ..api import read_capture

        with _warnings_to_log(self, instance):
            capture = read_capture(instance.data["capture"])
        instance.data["usdfaceCaptureSummary"] = {
            "vertices": int(capture.neutral.shape[0]), "shapes": len(capture.names),
            "train": len(capture.train), "test": len(capture.test)}
        if len(capture.train) == 0:
            from ..errors import CaptureError

            raise CaptureError("capture has no training expressions", path=instance.data["capture"],
                               fix="add train/<NNN>_<shape>.obj + .json frames")


class ValidateUsdFaceOptions(_pyblish.InstancePlugin):
    """The instance's ``usdfaceOptions`` are ones personalize takes, with values it accepts
    (:func:`usdface.api.check_personalize_options`, as ``usdface batch`` checks every row), so a typo or an
    option the face-transfer mode does not use fails validation instead of the extractor. Skipped when a
    registered extractor swaps in its own ``personalize`` (a studio's step takes its own options)."""

    order = _pyblish.ValidatorOrder
    families = [FAMILY]
    label = "Validate personalize options (usdface)"

    def process(self, instance):
        from ..api import check_item_options

        if not _default_personalize():
            return
        options = dict(instance.data.get("usdfaceOptions") or {})
        check_item_options(options)        # as check_personalize_options; dry_run, refused below, not offered
        # the files the options name (and the instance's take) present and readable, as 'usdface batch'
        # checks every row's before its first item: a missing take or pins file failed only in the extractor,
        # and so did a take of another kind (the avatar given as the take)
        from .batch import BatchItem, check_item_inputs

        data = instance.data
        check_item_inputs(BatchItem(str(data["avatar"]), str(data["capture"]), str(data["output"]),
                                    _personalize_options(instance)))
        if options.get("dry_run"):        # nothing written: the extractor failed on the missing layer
            from ..errors import OptionError

            raise OptionError("usdfaceOptions dry_run=True writes no layer, and a publish is the layer it "
                              "writes", path=instance.data.get("output"),
                              fix="drop dry_run from usdfaceOptions; preview with 'usdface personalize "
                                  "AVATAR CAPTURE --dry-run'")


class ValidateUsdFaceOutputs(_pyblish.InstancePlugin):
    """The files the extractors will write can be written, checked as the extractors check them, before any
    is: the layer (``output``: a USD name, not an input, not an existing file without ``force``, a place
    that takes it) and, with ``review``, the review page beside it. Without this, a publish whose review
    page was left by an earlier one wrote the layer and then failed in the review extractor, leaving the
    layer behind (and the retry failed on it: 'output layer exists'). The layer is not checked when a
    registered extractor swaps in its own ``personalize`` (a studio's step decides where it writes)."""

    order = _pyblish.ValidatorOrder
    families = [FAMILY]
    label = "Validate outputs (usdface)"

    def process(self, instance):
        from ..api import _check_correspondence_cache, personalize_inputs
        from ..errors import OutputExistsError
        from ..io.layers import check_output_path
        from .batch import check_review_page

        data = instance.data
        output = Path(data["output"])
        options = _personalize_options(instance)             # as the extractors take force and the take
        force, take = bool(options["force"]), options.pop("take", None)
        try:
            if _default_personalize():
                inputs = personalize_inputs(data["avatar"], data["capture"], take=take, **options)
                check_output_path(output, force, inputs=inputs)
                # the correspondence cache, an output too: in an input folder, where it cannot be written
                _check_correspondence_cache(options.get("correspondence"), inputs, outputs=[output])
            if _flag(instance, "review"):
                # as 'usdface batch' checks a row's review page (one function)
                check_review_page(output, force, inputs=[output, data["avatar"], data["capture"], take])
        except OutputExistsError as exc:     # the fix in a publish's terms: its fix named --force
            raise OutputExistsError(exc.message, path=exc.path, prim=exc.prim,
                                    fix="set the instance's data force=True (or force among its "
                                        "usdfaceOptions: in a batch manifest, the row's force column "
                                        "true) to replace it, or publish to another output") from None


class ExtractUsdFacePersonalized(_pyblish.InstancePlugin):
    """Personalize the avatar from the capture and write the layer; the written layer must pass the check."""

    order = _pyblish.ExtractorOrder
    families = [FAMILY]
    label = "Extract personalized avatar layer (usdface personalize)"

    @staticmethod
    def personalize(avatar, capture, output, **options):
        """The personalize step (a hook: a studio can swap in its own)."""
        from ..api import personalize_avatar

        return personalize_avatar(avatar, capture, output, **options)

    #: The built-in step (``personalize`` as shipped): options are validated only for it.
    default_personalize = personalize

    def process(self, instance):
        from ..api import check

        output = Path(instance.data["output"])
        options = _personalize_options(instance)
        existed = os.path.lexists(output)          # a layer replaced (force) is not removed on a failure
        self.log.info("personalizing %s with %s", instance.data["avatar"], instance.data["capture"])
        with _warnings_to_log(self, instance) as notes:
            result = self.personalize(instance.data["avatar"], instance.data["capture"], output, **options)
            report = getattr(result, "report", None)
            notes += [n for n in (report.get("warnings") or []) if isinstance(n, str)] \
                if isinstance(report, dict) else []
        written = Path(getattr(result, "out_path", None) or output)
        try:
            errors = [i for i in check(written, name_map=options.get("name_map")) if i.severity == "error"]
            if errors:
                from ..errors import UsdFaceError

                raise UsdFaceError(f"the written layer fails the check: {errors[0]}", path=written,
                                   fix="run 'usdface check' on the set-aside layer; report the problem to "
                                       "the usdface maintainers")
        except BaseException as exc:
            # a layer that fails (or breaks) the check is no publish: it stayed at the output, where the
            # retry then failed on it ('output layer exists'); kept aside for 'usdface check', as batch does
            if os.path.lexists(written):
                from .batch import set_aside

                aside = set_aside(written)
                add_to_message(exc, f"the layer was set aside as {aside.name}, not published")
            raise
        instance.data["usdfaceLayer"] = str(written)
        # whether this publish made the file (a later extractor's failure removes it) or replaced one (force)
        instance.data["usdfaceLayerNew"] = not existed or written.absolute() != output.absolute()
        instance.data.setdefault("files", []).append(str(written))
        instance.data.setdefault("representations", []).append(
            {"name": "usd", "ext": written.suffix.lstrip("."), "files": written.name,
             "stagingDir": str(written.parent)})
        self.log.info("wrote %s", written)


class ExtractUsdFaceReview(_pyblish.InstancePlugin):
    """With ``instance.data["review"]`` true: the review page of the written layer (``usdface review``),
    ``<layer>.review.html`` beside it, attached to the publish as a ``review`` representation."""

    order = _pyblish.ExtractorOrder + 0.1
    families = [FAMILY]
    label = "Extract review page (usdface review)"

    def process(self, instance):
        if not _flag(instance, "review") or not instance.data.get("usdfaceLayer"):
            return
        from .batch import write_review_page

        layer = Path(instance.data["usdfaceLayer"])
        options = _personalize_options(instance)       # the take the layer plays, the layer's force
        try:
            with _warnings_to_log(self, instance):      # stale inputs, a take's clipped weights, ...
                # the page a batch row with review true writes (one function)
                page = write_review_page(layer, instance.data.get("capture"), take=options.get("take"),
                                         force=bool(options["force"]))
        except BaseException as exc:
            # the publish failed after the layer was written: the layer stayed on disk (and in the
            # instance's files, for an integrator), and the retry failed on it ('output layer exists')
            add_to_message(exc, _withdraw_layer(instance, layer))
            raise
        instance.data["usdfaceReview"] = str(page)
        instance.data.setdefault("files", []).append(str(page))
        instance.data.setdefault("representations", []).append(
            {"name": "review", "ext": "html", "files": page.name, "stagingDir": str(page.parent)})
        self.log.info("wrote %s", page)


def _withdraw_layer(instance, layer: Path) -> str:
    """Take the layer the layer extractor wrote off the instance's files and representations, and remove it
    when this publish made it (``instance.data["usdfaceLayerNew"]``); one that replaced an earlier layer
    (``force``) is left. Returns what was done, for the error."""
    data = instance.data
    data.pop("usdfaceLayer", None)
    data["files"] = [f for f in data.get("files", []) if Path(f) != layer]
    data["representations"] = [r for r in data.get("representations", [])
                               if not (r.get("name") == "usd" and r.get("files") == layer.name
                                       and Path(r.get("stagingDir", "")) == layer.parent)]
    if not data.pop("usdfaceLayerNew", False):      # replaced an earlier one, or not known to be new
        return (f"the layer {layer.name} this publish wrote replaced the earlier one (force) and is left "
                "there, not published")
    try:
        layer.unlink()
    except FileNotFoundError:
        pass
    except OSError as err:
        return f"the layer {layer.name} this publish wrote could not be removed ({err}): delete it"
    return f"the layer {layer.name} this publish wrote was removed: a failed publish leaves nothing"


#: The plugins, in publish order.
PLUGINS = (CollectUsdFaceItems, ValidateUsdFaceRig, ValidateUsdFaceCapture, ValidateUsdFaceOptions,
           ValidateUsdFaceOutputs, ExtractUsdFacePersonalized, ExtractUsdFaceReview)


class _RefusalsAsOneLine(logging.Filter):
    """Pyblish logs a failed plugin with ``log.exception`` on its ``pyblish.plugin`` logger: the traceback
    as the message and again as the record's exception, so a plain refusal (an output that exists, a bad
    option) printed two tracebacks around its one line (stop 54, a TD's trial). A record whose exception is
    a :class:`usdface.errors.UsdFaceError` is logged as that error's one line (file, prim, fix), as the
    command line prints it; any other exception (a bug, usdface's or a studio plugin's) keeps its
    traceback. The error itself, traceback included, stays in ``context.data["results"]``."""

    def filter(self, record: logging.LogRecord) -> bool:
        from ..errors import UsdFaceError

        error = record.exc_info[1] if record.exc_info else None
        if isinstance(error, UsdFaceError):
            record.msg, record.args = str(error), ()
            record.exc_info = record.exc_text = None
        return True


_REFUSALS = _RefusalsAsOneLine()
#: The logger Pyblish logs a failed plugin's exception on (``pyblish.plugin.__explicit_process``).
_PLUGIN_LOG = "pyblish.plugin"


def register() -> None:
    """Register usdface's plugins with Pyblish (idempotent), and log their refusals as one line each
    (:class:`_RefusalsAsOneLine`)."""
    for plugin in PLUGINS:
        if plugin not in _pyblish.registered_plugins():
            _pyblish.register_plugin(plugin)
    logging.getLogger(_PLUGIN_LOG).addFilter(_REFUSALS)          # once: a filter is added only once


def deregister() -> None:
    """Remove usdface's plugins from Pyblish (and the one-line logging of their refusals)."""
    for plugin in PLUGINS:
        if plugin in _pyblish.registered_plugins():
            _pyblish.deregister_plugin(plugin)
    logging.getLogger(_PLUGIN_LOG).removeFilter(_REFUSALS)
