"""Driving rules that read only observations: the scripted mainline drivers and ego rules
(`scripted`), and gap acceptance with the shield built on it (`gap_acceptance`)."""

from marlmerge.policies.gap_acceptance import GapAcceptancePolicy, GapShield
from marlmerge.policies.scripted import IdmEgoPolicy, ScriptedHighwayPolicy, constant_speed_action

__all__ = [
    "GapAcceptancePolicy",
    "GapShield",
    "IdmEgoPolicy",
    "ScriptedHighwayPolicy",
    "constant_speed_action",
]
