"""usdface's face-rig rules inside OpenUSD's validation framework, and Pixar's validators next to them.

usd-core 26.x replaced ``UsdUtils.ComplianceChecker`` with ``pxr.UsdValidation`` (``ValidationRegistry``,
``ValidationContext``, ``Validator``). Its registry accepts validators written in Python
(``ValidationRegistry().RegisterStageValidator(ValidatorMetadata, callable)``), so every rule of
:mod:`usdface.pipeline.check` is registered as a real OpenUSD stage validator:

* name ``usdfaceValidators:<RuleId>`` (e.g. ``usdfaceValidators:ArkitNames``), keyword ``UsdFaceValidators``;
* errors named after the rule, one ``ValidationErrorSite`` at the offending prim, the fix in the message.

Any tool that runs a ``ValidationContext`` over all validators, or over the ``UsdFaceValidators``
keyword, then runs them::

    from pxr import Usd, UsdValidation
    from usdface.pipeline.validators import register_validators
    register_validators()
    ctx = UsdValidation.ValidationContext(keywords=["UsdFaceValidators"])
    errors = ctx.Validate(Usd.Stage.Open("avatar.usdc"))

:func:`validate_stage` / :func:`validate_file` run Pixar's own validators together with the face-rig
rules and merge both into one sorted list of :class:`usdface.pipeline.check.Issue` (duplicates of the same
finding, such as a missing ``upAxis`` reported by both, are kept once). :class:`FaceRigRuleChecker` offers
the same rules in the ``BaseRuleChecker`` style of older pipelines and NVIDIA's asset validator.
"""

from __future__ import annotations

from .check import ERROR, INFO, RULES, WARNING, Issue, check, sort_issues

#: The keyword under which usdface's validators are registered.
KEYWORD = "UsdFaceValidators"
#: Validator name prefix.
PREFIX = "usdfaceValidators"

#: Pixar error names that repeat a usdface finding (kept once, as usdface's, which carries the fix).
_DUPLICATES = {
    "MissingDefaultPrim": ("StageMetadata", "defaultPrim"),
    "MissingMetersPerUnitMetadata": ("StageMetadata", "metersPerUnit"),
    "MissingUpAxisMetadata": ("StageMetadata", "upAxis"),
    "MissingSkelBindingAPI": ("SkelBinding", "SkelBindingAPI"),
}


def validator_name(rule_id: str) -> str:
    """OpenUSD validator name of a usdface rule: ``usdfaceValidators:<rule_id>``."""
    return f"{PREFIX}:{rule_id}"


def _severity_to_pixar(severity: str):
    from pxr import UsdValidation

    return {ERROR: UsdValidation.ValidationErrorType.Error, WARNING: UsdValidation.ValidationErrorType.Warn,
            INFO: UsdValidation.ValidationErrorType.Info}[severity]


def _severity_from_pixar(kind) -> str:
    from pxr import UsdValidation

    t = UsdValidation.ValidationErrorType
    if kind == t.Error:
        return ERROR
    if kind == t.Warn:
        return WARNING
    return INFO


def _make_validator(rule_id: str):
    def validate(stage, time_range=None):
        from pxr import Sdf, UsdValidation

        errors = []
        for issue in check(stage, [rule_id]):
            site = UsdValidation.ValidationErrorSite(stage, Sdf.Path(issue.prim))
            message = issue.message + (f" (fix: {issue.fix})" if issue.fix else "")
            errors.append(UsdValidation.ValidationError(rule_id, _severity_to_pixar(issue.severity), [site],
                                                        message))
        return errors

    return validate


def register_validators() -> list[str]:
    """Register every rule of :data:`usdface.pipeline.check.RULES` with OpenUSD's ``ValidationRegistry``
    (idempotent). Returns the validator names. usdface's schemas are registered first: the validation
    registry builds USD's schema registry, which takes no plugins afterwards."""
    from .. import schemas

    schemas.register()
    from pxr import UsdValidation

    registry = UsdValidation.ValidationRegistry()
    names = []
    for rule_id, (_fn, doc) in RULES.items():
        name = validator_name(rule_id)
        names.append(name)
        if registry.HasValidator(name):
            continue
        meta = UsdValidation.ValidatorMetadata(name=name, doc=f"usdface face-rig rule: {doc}",
                                               keywords=[KEYWORD], schemaTypes=[], isTimeDependent=False,
                                               isSuite=False)
        registry.RegisterStageValidator(meta, _make_validator(rule_id))
    return names


def pixar_validators():
    """All of OpenUSD's registered validators except usdface's own."""
    from pxr import UsdValidation

    registry = UsdValidation.ValidationRegistry()
    return [v for v in registry.GetOrLoadAllValidators()
            if not v.GetMetadata().name.startswith(PREFIX + ":")]


def run_pixar_validators(stage) -> list[Issue]:
    """OpenUSD's own validators (``UsdValidation.ValidationContext``) on ``stage``, as :class:`Issue` s."""
    from pxr import UsdValidation

    context = UsdValidation.ValidationContext(pixar_validators())
    issues = []
    for err in context.Validate(stage):
        if err.HasNoError():
            continue
        prims = [str(s.GetPrim().GetPath()) for s in err.GetSites() if s.IsValid() and s.GetPrim()]
        validator = err.GetValidator()
        rule = validator.GetMetadata().name if validator else err.GetIdentifier()
        issues.append(Issue(_severity_from_pixar(err.GetType()), f"{rule}.{err.GetName()}",
                            prims[0] if prims else "/", err.GetMessage(), "", source="pixar"))
    return issues


def merge_issues(ours: list[Issue], pixar: list[Issue]) -> list[Issue]:
    """One report: usdface's issues plus Pixar's, dropping Pixar findings that repeat one of ours."""
    kept = list(ours)
    for issue in pixar:
        name = issue.rule.rsplit(".", 1)[-1]
        dup = _DUPLICATES.get(name)
        if dup and any(o.rule == dup[0] and dup[1] in o.message for o in ours):
            continue
        kept.append(issue)
    return sort_issues(kept)


def validate_stage(stage, pixar: bool = True, rules=None, name_map=None, face_mesh=None) -> list[Issue]:
    """Face-rig rules (and, with ``pixar=True``, OpenUSD's own validators) on an open stage, merged;
    ``name_map``: the studio's {channel: ARKit name} map (:func:`usdface.io.name_map.read_name_map`);
    ``face_mesh``: personalize's ``--face-mesh`` (a stage with several characters names the one meant)."""
    ours = check(stage, rules, name_map=name_map, face_mesh=face_mesh)
    return merge_issues(ours, run_pixar_validators(stage)) if pixar else ours


def open_stage(path):
    """Open a USD file for checking; raises :class:`usdface.errors.InputFileError` naming the file (missing,
    a folder or pipe, unreadable, composition errors such as a missing or cyclic sublayer)."""
    import usdface.io  # noqa: F401  (registers usdface's schemas before the first stage)
    from usdface.io.usd_open import open_usd_stage

    return open_usd_stage(path, "file", "pass an existing .usd/.usda/.usdc file")


def validate_file(path, pixar: bool = True, rules=None, name_map=None, face_mesh=None) -> list[Issue]:
    """Open ``path`` and run :func:`validate_stage`. The file is never modified."""
    return validate_stage(open_stage(path), pixar=pixar, rules=rules, name_map=name_map, face_mesh=face_mesh)


class FaceRigRuleChecker:
    """The face-rig rules as a ``BaseRuleChecker``-style rule object.

    Follows the interface of ``UsdUtils.ComplianceChecker``'s ``BaseRuleChecker`` (gone from usd-core 26.x
    but still the shape of NVIDIA's ``omni.asset_validator`` rules and many studio checkers):
    ``GetDescription()``, ``CheckStage(stage)``, ``CheckLayer``/``CheckPrim``/``CheckZipFile``/
    ``CheckDependencies``/``CheckUnresolvedPaths`` (no-ops: the rules are stage-level), ``ResetCaches()``,
    and the results in ``GetFailedChecks()`` (errors), ``GetWarnings()``, ``GetErrors()`` (internal
    failures), as strings. ``issues`` keeps the structured :class:`Issue` list.

    ``ResetCaches()`` keeps the results, as ``BaseRuleChecker``'s does: a compliance checker calls it after
    ``CheckStage`` each time it selects another variant (a usdface layer's ``usdfacePersonalization``), and
    it emptied the findings, so such a checker reported none. Results gather over the checker's life.
    """

    def __init__(self, verbose: bool = False, consumerLevelChecks: bool = False,  # noqa: N803
                 assetLevelChecks: bool = True):  # noqa: N803
        from .. import schemas

        # as register_validators: a compliance checker makes its rule objects before it opens the stage,
        # and the stage's schema registry then takes no plugins (the checker, made first, opened a stage
        # and warned that the registry was created before usdface registered its schemas; a user trial)
        schemas.register()
        self._verbose = verbose
        self._consumerLevelChecks = consumerLevelChecks
        self._assetLevelChecks = assetLevelChecks
        self.issues: list[Issue] = []
        self._failedChecks: list[str] = []
        self._errors: list[str] = []
        self._warnings: list[str] = []

    @staticmethod
    def GetDescription() -> str:  # noqa: N802
        return "usdface ARKit face-rig rules: " + "; ".join(doc for _fn, doc in RULES.values())

    def ResetCaches(self) -> None:  # noqa: N802
        """Nothing to reset: the rules keep no caches (called on every variant selection; not the results)."""

    def CheckStage(self, usdStage) -> None:  # noqa: N802, N803
        try:
            found = check(usdStage)
        except Exception as exc:  # a rule crashing is an internal error of the checker, not of the asset
            self._errors.append(f"usdface rules failed: {exc}")
            return
        self.issues.extend(found)
        for issue in found:
            (self._failedChecks if issue.severity == ERROR else self._warnings).append(str(issue))

    def CheckDiagnostics(self, diagnostics) -> None:  # noqa: N802
        pass

    def CheckUnresolvedPaths(self, unresolvedPaths) -> None:  # noqa: N802, N803
        pass

    def CheckDependencies(self, usdStage, layerDeps, assetDeps) -> None:  # noqa: N802, N803
        pass

    def CheckLayer(self, layer) -> None:  # noqa: N802
        pass

    def CheckZipFile(self, zipFile, packagePath) -> None:  # noqa: N802, N803
        pass

    def CheckPrim(self, prim) -> None:  # noqa: N802
        pass

    def GetFailedChecks(self) -> list[str]:  # noqa: N802
        return list(self._failedChecks)

    def GetErrors(self) -> list[str]:  # noqa: N802
        return list(self._errors)

    def GetWarnings(self) -> list[str]:  # noqa: N802
        return list(self._warnings)
