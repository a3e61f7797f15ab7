"""The takeover keys: the one place their default names are written.

:class:`~pe_rlhf.transforms.InterventionTransform` writes them under ``next`` (renamable with its
``out_keys``, in the order of :data:`OUT_KEYS`); :class:`~pe_rlhf.objectives.PERLHFLoss` reads
``behavior_action``, ``intervention``, ``intervention_start`` and ``intervention_cost`` (renamable with
``set_keys``); :class:`~pe_rlhf.wrappers.InterventionWrapper` reports them in gymnasium's ``info``.

===========================  ==================================================================
``behavior_action`` (A,)     the executed action ``a_exec`` (float32)
``intervention`` (1,)        the mentor held control this step (bool)
``intervention_start`` (1,)  first step of a takeover (bool)
``intervention_cost`` (1,)   ``1 - cos(a_AV, a_exec)`` at a start, else 0 (float32)
``mentor_action`` (A,)       the mentor's proposal (float32)
``physics_action`` (A,)      the physics proposal during a PE-RLHF takeover, else zeros (float32)
``mentor_selected`` (1,)     the mentor's action was executed in a takeover (bool)
===========================  ==================================================================

:class:`~pe_rlhf.transforms.SafetyShield` writes its own under ``next`` (renamable with its ``out_keys``, in the
order of :data:`SHIELD_OUT_KEYS`); :class:`~pe_rlhf.wrappers.SafetyShieldWrapper` reports them in ``info``.

=================================  ============================================================
``shield_override`` (1,)           the shield executed physics' action this step (bool)
``shielded_action`` (A,)           the action executed (float32)
``policy_time_to_failure`` (1,)    the forecast of the policy's action [s] (float32)
``physics_time_to_failure`` (1,)   the forecast of physics' action [s] (float32)
=================================  ============================================================
"""

from __future__ import annotations

BEHAVIOR_ACTION = "behavior_action"
INTERVENTION = "intervention"
INTERVENTION_START = "intervention_start"
INTERVENTION_COST = "intervention_cost"
MENTOR_ACTION = "mentor_action"
PHYSICS_ACTION = "physics_action"
MENTOR_SELECTED = "mentor_selected"

OUT_KEYS = (BEHAVIOR_ACTION, INTERVENTION, INTERVENTION_START, INTERVENTION_COST, MENTOR_ACTION, PHYSICS_ACTION,
            MENTOR_SELECTED)
ACTION_KEYS = (BEHAVIOR_ACTION, MENTOR_ACTION, PHYSICS_ACTION)  # float32 (A,)
FLAG_KEYS = (INTERVENTION, INTERVENTION_START, MENTOR_SELECTED)  # bool (1,)
COST_KEY = INTERVENTION_COST  # float32 (1,)

SHIELD_OVERRIDE = "shield_override"
SHIELDED_ACTION = "shielded_action"
POLICY_TIME_TO_FAILURE = "policy_time_to_failure"
PHYSICS_TIME_TO_FAILURE = "physics_time_to_failure"
SHIELD_OUT_KEYS = (SHIELD_OVERRIDE, SHIELDED_ACTION, POLICY_TIME_TO_FAILURE, PHYSICS_TIME_TO_FAILURE)

__all__ = ["ACTION_KEYS", "BEHAVIOR_ACTION", "COST_KEY", "FLAG_KEYS", "INTERVENTION", "INTERVENTION_COST",
           "INTERVENTION_START", "MENTOR_ACTION", "MENTOR_SELECTED", "OUT_KEYS", "PHYSICS_ACTION",
           "PHYSICS_TIME_TO_FAILURE", "POLICY_TIME_TO_FAILURE", "SHIELDED_ACTION", "SHIELD_OUT_KEYS", "SHIELD_OVERRIDE"]
