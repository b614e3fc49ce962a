"""When a level answer may be called confident: the rule, in one place (README "When to trust the level names").

Every labelling of the clicks has been registered and scored (``labelling_fit``: f = (1 - GC) + landmark term
+ rotation prior, lower is better). The *reference* is the surgeon's names when given, else the best labelling.

1. margin ``d = f(best other) - f(reference)``;
2. provisional verdict: ``d >= margin`` confident; ``|d| < margin`` ambiguous; ``d <= -margin`` contradicted
   (names given only: the image prefers another labelling);
3. a confident or contradicted verdict stands only when the labelling it rests on (the best one, ``winner``)
   passes every check against the labelling it beat (``rival``):

   - image agreement: ``A(winner) >= min_similarity`` - a labelling that matches the image poorly has won
     nothing, however large its lead. A is the winner's GC, or the GC of the same pose on the equalised X-ray when
     higher (``agreement``: a processed display lowers the GC of the conversion it was registered on);
   - landmark fit: ``mPDE(winner) <= landmark_ratio * min(mPDE(rival), mPDE(best fit)) + landmark_slack_mm``,
     the best fit being the other registered labelling the clicks fit best (one whose refinement stopped as
     hopeless counts with the fit it reached: ``early_stop``) - a labelling the clicks fit clearly
     worse than another has won on image texture alone (seen: GC 0.364 against 0.316 while the clicks fitted
     3.19 mm against 1.66 mm, one level off; and, stop 45, a winner one level off at GC 0.46 and 2.71 mm over a
     runner-up at 3.44 mm, while the right labelling, third, fitted them at 1.00 mm; such a best fit is first given
     the leaders' searches, ``levels._challenge_best_fit``, and then won) - and
     ``mPDE(winner) <= max_landmark_mpde_mm``: the clicks must fit the winner itself (seen: labellings five levels
     off won at 6 mm);
   - stability: the leading two labellings were refitted, each from the other's pose, from their own tilted about L
     and restarted afresh (``levels._confirm_leaders``, ``_tilt_leaders``, ``_restart_leaders``), and the same one
     led;
   - appearance: the X-ray's polarity was clear (or set by the user and not contradicted; a file stating its
     polarity and an image disagreeing is a conflict) and it matches the CT best as stored by a clear lead, not
     mirrored or turned (``image.appearance.trusted_appearance``).

   Any failed check turns the verdict into **ambiguous**, with the reasons in words.

Without clicks the verdict is at best **proposed** (never confident); the image-agreement and appearance checks
apply, the landmark one cannot.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from carmreg.logic.registration.labelling_fit import LabellingFit


@dataclass
class ConfidenceRule:
    margin: float = 0.02              # objective difference between confident and ambiguous
    min_similarity: float = 0.40      # image agreement at the winner's pose, below which nothing is confirmed
    # (chosen on the appearance benchmark's tune half: the highest floor that costs no confident right answer
    # there - right answers reached GC >= 0.41, labellings that won wrongly up to 0.47, stopped by other checks)
    landmark_ratio: float = 1.5       # the winner's click mPDE may exceed the rival's by this factor ...
    landmark_slack_mm: float = 0.5    # ... plus this (detector mm; clicks carry ~1-3 mm of noise and motion)
    max_landmark_mpde_mm: float = 4.0  # and never more than this in absolute terms (tune half: right winners
    # <= 2.9 mm; wrong ones 1.9-8.8 mm; a mirrored display confidently named at 7.4 mm)


@dataclass
class Verdict:
    status: str                       # confident | ambiguous | contradicted | proposed
    margin: float
    winner: LabellingFit              # the best labelling
    runner_up: LabellingFit | None    # the best other (when the reference is the winner) or the winner
    reasons: list = field(default_factory=list)   # why a verdict is ambiguous (a close margin, failed checks)
    checks: dict = field(default_factory=dict)    # each check's values and pass/fail


@dataclass
class Evidence:
    """The numbers the rule judges (all recorded in ``result.json["level_check"]["checks"]``): the winner's image
    agreement (GC), the click mPDE (detector mm) of the winner and of the labelling it beat (nan: none), whether
    the leading two kept their order when refitted from each other's pose, and whether the X-ray's appearance is
    trusted."""

    gc: float                                   # the winner's image agreement (``LabellingFit.agreement``)
    winner_mpde_mm: float = float("nan")
    rival_mpde_mm: float = float("nan")
    stable: bool = True
    appearance_ok: bool = True
    winner_labels: tuple = ()
    rival_labels: tuple = ()
    gc_converted: float = float("nan")         # the winner's GC on the X-ray as converted (its score's)
    best_fit_mpde_mm: float = float("nan")     # the other registered labelling the clicks fit best (nan: none)
    best_fit_labels: tuple = ()

    @classmethod
    def of(cls, winner: LabellingFit, rival: LabellingFit | None, stable: bool, appearance_ok: bool,
           best_fit: LabellingFit | None = None) -> Evidence:
        return cls(winner.agreement, winner.mpde_mm, rival.mpde_mm if rival is not None else float("nan"),
                   stable, appearance_ok, tuple(winner.labels), tuple(rival.labels) if rival is not None else (),
                   winner.similarity, best_fit.mpde_mm if best_fit is not None else float("nan"),
                   tuple(best_fit.labels) if best_fit is not None else ())

    def landmark_rival(self) -> tuple[float, tuple]:
        """(mPDE, labels) of the labelling the winner's click fit is held against: the rival, or the best-fitting
        other labelling when the clicks fit that one better."""
        if np.isfinite(self.best_fit_mpde_mm) and not self.best_fit_mpde_mm >= self.rival_mpde_mm:
            return self.best_fit_mpde_mm, self.best_fit_labels
        return self.rival_mpde_mm, self.rival_labels

    @classmethod
    def from_checks(cls, checks: dict) -> Evidence:
        """The evidence as ``check_results`` recorded it (for re-judging recorded runs under another rule)."""
        fit = checks.get("landmark_fit") or {}

        def number(value) -> float:  # JSON keeps nan and inf as null
            return float("nan") if value is None else float(value)
        return cls(float(checks["image_agreement"]["gc"]), number(fit.get("winner_mpde_mm")),
                   number(fit.get("rival_mpde_mm")), bool(checks["stability"]["ok"]), bool(checks["appearance"]["ok"]),
                   best_fit_mpde_mm=number(fit.get("best_fit_mpde_mm")))


POOR_AGREEMENT_CAUSES = ("bone barely shows (a large patient, a low dose), or the X-ray is not of this CT's patient "
                         "and levels")
"""What the image-agreement check's reason tells the user to look for: seen on the appearance benchmark's large
patients, and on real X-rays not of the CT (``Testing/Benchmarks/bench_real_xrays.py``: a shoulder frame with clicks,
GC 0.22-0.395 at the best labelling; another patient's chest radiograph without clicks, 0.35)."""


def landmark_limit_mm(rival_mpde_mm: float, rule: ConfidenceRule) -> float:
    """The click mPDE (detector mm) a winner may have against a rival's: ``landmark_ratio`` x the rival's +
    ``landmark_slack_mm``, never above ``max_landmark_mpde_mm`` (no rival, nan: the cap alone)."""
    relative = rule.landmark_ratio * rival_mpde_mm + rule.landmark_slack_mm if np.isfinite(rival_mpde_mm) else np.inf
    return float(min(relative, rule.max_landmark_mpde_mm))


def check_results(e: Evidence, rule: ConfidenceRule, landmarks: bool = True) -> tuple[dict, list[str]]:
    """Each check's values and pass/fail, and the reasons in words of those that failed (module docstring)."""
    checks, reasons = {}, []
    checks["image_agreement"] = {"gc": e.gc, "gc_as_converted": e.gc_converted, "min": rule.min_similarity,
                                 "ok": bool(e.gc >= rule.min_similarity)}
    if not checks["image_agreement"]["ok"]:
        reasons.append(f"the image agrees poorly even with the best labelling (GC {e.gc:.2f} < "
                       f"{rule.min_similarity:.2f}: {POOR_AGREEMENT_CAUSES})")
    if landmarks and np.isfinite(e.winner_mpde_mm):
        against_mpde_mm, against_labels = e.landmark_rival()
        limit = landmark_limit_mm(against_mpde_mm, rule)
        ok = bool(e.winner_mpde_mm <= limit)
        checks["landmark_fit"] = {"winner_mpde_mm": e.winner_mpde_mm, "rival_mpde_mm": e.rival_mpde_mm,
                                  "best_fit_mpde_mm": e.best_fit_mpde_mm, "best_fit_labels": list(e.best_fit_labels),
                                  "limit_mm": limit, "ok": ok}
        winner = ", ".join(e.winner_labels) or "the winner"
        if not ok and e.winner_mpde_mm > rule.max_landmark_mpde_mm:
            reasons.append(f"the clicks fit {winner} poorly ({e.winner_mpde_mm:.1f} mm > "
                           f"{rule.max_landmark_mpde_mm:.1f} mm)")
        elif not ok:
            reasons.append(f"the clicks fit {winner} clearly worse ({e.winner_mpde_mm:.1f} mm) than "
                           f"{', '.join(against_labels) or 'its rival'} ({against_mpde_mm:.1f} mm)")
    checks["stability"] = {"ok": bool(e.stable)}
    if not e.stable:
        reasons.append("the leading labelling changed when the two best were searched again (from each other's "
                       "pose, or afresh)")
    checks["appearance"] = {"ok": bool(e.appearance_ok)}
    if not e.appearance_ok:
        reasons.append("the X-ray's appearance is not clear (bone dark or bright, or a mirrored or turned display)")
    return checks, reasons


def margin_reason(d: float, e: Evidence, rule: ConfidenceRule, image_only: bool = False) -> str:
    """Why a margin under ``rule.margin`` leaves the answer ambiguous, in words (``image_only``: the labellings
    are poses named by the level at the image centre)."""
    if image_only:
        return (f"a pose with {', '.join(e.rival_labels)} at the image centre fits the image about as well as the "
                f"best, with {', '.join(e.winner_labels)} (margin {d:+.3f}, under {rule.margin:.2f})")
    return (f"the image fits {', '.join(e.winner_labels)} and {', '.join(e.rival_labels)} about equally (margin "
            f"{d:+.3f}, under {rule.margin:.2f})")


def judge(d: float, e: Evidence, rule: ConfidenceRule) -> tuple[str, list[str], dict]:
    """(status, reasons, checks) from the margin ``d`` of the reference labelling (the surgeon's names, or the
    best labelling) over the best other, and the evidence: steps 2 and 3 of the module docstring. The reasons
    of an ambiguous verdict: the margin when it decides (``margin_reason``), and every failed check."""
    status = "confident" if d >= rule.margin else ("ambiguous" if d > -rule.margin else "contradicted")
    checks, reasons = check_results(e, rule)
    if status == "ambiguous":
        return status, [margin_reason(d, e, rule)] + reasons, checks
    if reasons:
        return "ambiguous", reasons, checks
    return status, [], checks


def best_click_fit(fits: list[LabellingFit], winner: LabellingFit) -> LabellingFit | None:
    """The registered labelling other than ``winner`` the clicks fit best (lowest click mPDE; one stopped as
    hopeless counts with the fit it reached), None when there is none: the landmark check's best fit
    (``decide``)."""
    fitted = [f for f in fits if f.refined and f is not winner and np.isfinite(f.mpde_mm)]
    return min(fitted, key=lambda f: f.mpde_mm) if fitted else None


def decide(fits: list[LabellingFit], given: LabellingFit | None, rule: ConfidenceRule, *, stable: bool = True,
           appearance_clear: bool = True) -> Verdict:
    """The verdict over the registered labellings (module docstring); ``given``: the surgeon's labelling."""
    ranked = sorted((f for f in fits if f.refined), key=lambda f: f.score)
    winner = ranked[0]
    reference = given if given is not None else winner
    others = [f for f in ranked if f is not reference]
    if not others:
        status, reasons, checks = judge(float("inf"), Evidence.of(winner, None, stable, appearance_clear), rule)
        return Verdict(status, float("inf"), winner, None, reasons, checks)
    d = float(others[0].score - reference.score)
    runner_up = others[0] if reference is winner else winner
    rival = others[0] if reference is winner else reference
    best_fit = best_click_fit(ranked, winner)
    status, reasons, checks = judge(d, Evidence.of(winner, rival, stable, appearance_clear, best_fit), rule)
    return Verdict(status, d, winner, runner_up, reasons, checks)


def decide_image_only(ranked: list[LabellingFit], rule: ConfidenceRule, *, appearance_clear: bool = True) -> Verdict:
    """No clicks: proposed when the best pose leads by ``margin`` and passes the image and appearance checks."""
    winner = ranked[0]
    runner_up = ranked[1] if len(ranked) > 1 else None
    d = float(runner_up.score - winner.score) if runner_up is not None else float("inf")
    evidence = Evidence.of(winner, runner_up, True, appearance_clear)
    checks, reasons = check_results(evidence, rule, landmarks=False)
    if d < rule.margin:
        return Verdict("ambiguous", d, winner, runner_up, [margin_reason(d, evidence, rule, True)] + reasons, checks)
    return Verdict("ambiguous" if reasons else "proposed", d, winner, runner_up, reasons, checks)
