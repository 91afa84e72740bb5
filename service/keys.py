"""Zenoh key expressions of the contract (CONTRACT.md §1), built and parsed in one place."""

from __future__ import annotations

import re
from dataclasses import dataclass

_ID = r"[A-Za-z0-9_-]{1,64}"


@dataclass(frozen=True)
class Keys:
    prefix: str = "fusion"

    def site(self, radar_id: str) -> str:
        return f"{self.prefix}/radar/{radar_id}/site"

    def plots(self, radar_id: str) -> str:
        return f"{self.prefix}/radar/{radar_id}/plots"

    def ais(self, source_id: str) -> str:
        return f"{self.prefix}/ais/{source_id}/reports"

    def tracks(self, radar_id: str) -> str:
        return f"{self.prefix}/radar/{radar_id}/tracks"

    def pairs(self, radar_a: str, radar_b: str) -> str:
        return f"{self.prefix}/pairs/{radar_a}/{radar_b}"

    def input(self, kind: str, source_id: str) -> str:
        """The input key of ``kind`` (``site``, ``plots`` or ``ais``) for a source."""
        return {"site": self.site, "plots": self.plots, "ais": self.ais}[kind](source_id)

    @property
    def errors(self) -> str:
        return f"{self.prefix}/errors"

    @property
    def status(self) -> str:
        return f"{self.prefix}/status"

    @property
    def pairs_all(self) -> str:
        return f"{self.prefix}/pairs/**"

    @property
    def radar_inputs(self) -> str:
        return f"{self.prefix}/radar/*/*"

    @property
    def ais_inputs(self) -> str:
        return f"{self.prefix}/ais/*/reports"

    def classify(self, key: str) -> tuple[str, str] | None:
        """``("site"|"plots"|"ais", id)`` for an input key of this prefix, else ``None``."""
        rest = key[len(self.prefix) + 1 :] if key.startswith(self.prefix + "/") else None
        if rest is None:
            return None
        m = re.fullmatch(rf"radar/({_ID})/(site|plots)", rest)
        if m:
            return m.group(2), m.group(1)
        m = re.fullmatch(rf"ais/({_ID})/reports", rest)
        if m:
            return "ais", m.group(1)
        return None
