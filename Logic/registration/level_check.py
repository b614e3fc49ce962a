"""The level answer as the front doors show it and ``result.json["level_check"]`` records it: ``LevelCheck``.

Made by the levels stage (``levels.LevelIdentification.summary``); read back from a result file or a session with
``LevelCheck.from_dict`` (missing fields take their defaults, so older files still open). Plain data, no heavy
imports: the window imports it at start.

Fields: ``mode`` named | partly_named | unnamed | image_only; ``status`` confident | ambiguous | contradicted |
proposed; ``margin`` the objective difference of the reference labelling over the best other (level_confidence;
None or inf when there was no other); ``message`` the answer in words; ``reasons`` why a lead was lowered to
ambiguous; ``checks`` the confidence rule's evidence and verdicts; ``assigned_labels`` the name of each identified
click, in the order of ``click_indices`` (indices into the clicks as given); ``winner_labels`` /
``runner_up_labels`` the best labelling and the best other, head to sacrum; ``visible_labels`` (no clicks) the
levels in the exposed field at the winning pose; ``hypotheses`` every labelling tried (``LabellingFit.as_dict``);
``withheld`` why no level is named ("" when the names stand): the X-ray was refused (``withheld_for``).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field


@dataclass
class LevelCheck:
    mode: str
    status: str
    margin: float | None = None
    message: str = ""
    reasons: list = field(default_factory=list)
    checks: dict = field(default_factory=dict)
    assigned_labels: list = field(default_factory=list)
    click_indices: list = field(default_factory=list)
    winner_labels: list = field(default_factory=list)
    runner_up_labels: list | None = None
    visible_labels: list = field(default_factory=list)
    hypotheses: list = field(default_factory=list)
    withheld: str = ""

    @property
    def contradicted(self) -> bool:
        return self.status == "contradicted"

    def names(self) -> list[str]:
        """The levels the answer names: those in view without clicks, else the clicks' assigned names."""
        return list(self.visible_labels if self.mode == "image_only" else self.assigned_labels)

    def withheld_for(self, reason: str) -> LevelCheck:
        """This answer with no level named, because of ``reason`` (the X-ray refused: a mirrored or turned
        display, on which a pose and names are a guess under the wrong geometry): status ambiguous, whatever the
        contest said (it judged the image as stored). The margin, checks, winner, runner-up and hypotheses stay,
        as the record of what the contest found; the names given to the clicks or seen in the image are dropped,
        so no front door shows or offers them."""
        return dataclasses.replace(self, status="ambiguous", assigned_labels=[], visible_labels=[], withheld=reason,
                                   message=f"level names WITHHELD: {reason}")

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, doc: dict | None) -> LevelCheck | None:
        """A LevelCheck from ``result.json`` or a session (None for none; unknown keys ignored)."""
        if not doc or not isinstance(doc, dict) or not doc.get("status"):
            return None
        names = {f.name for f in dataclasses.fields(cls)}
        return cls(**{k: v for k, v in doc.items() if k in names} | {"mode": str(doc.get("mode", "")),
                                                                      "status": str(doc["status"])})
