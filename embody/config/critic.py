"""`critic`: the refinement loop, the geometric critic and the VLM client."""

from __future__ import annotations

from typing import Literal

from pydantic import Field

from embody.config.base import Section


class VLMConfig(Section):
    #: OpenAI-compatible endpoint (vLLM `/v1`, Ollama `http://localhost:11434/v1`, llama-server).
    base_url: str = "http://localhost:8000/v1"
    model: str = "Qwen/Qwen2.5-VL-7B-Instruct"
    #: Name of the environment variable holding the API key (the key itself is never config).
    api_key_env: str = "EMBODY_VLM_API_KEY"
    #: Local servers often need no key; when false a missing key sends no Authorization header.
    api_key_required: bool = True
    #: Longest one request may take, from connecting to the last byte of the answer (a
    #: deadline over all reads, not per read: a server trickling bytes cannot stretch it).
    timeout_s: float = Field(60.0, gt=0.0, le=3600.0)
    max_retries: int = Field(3, ge=0, le=20)
    backoff_s: float = Field(1.0, ge=0.0, le=60.0)
    max_backoff_s: float = Field(30.0, ge=0.0, le=600.0)
    #: Requests one run may send at most (retries included), so a bad loop cannot run up a bill.
    request_budget: int = Field(64, ge=1, le=100_000)
    temperature: float = Field(0.0, ge=0.0, le=2.0)
    max_tokens: int = Field(512, ge=16, le=32_768)
    #: Prompt file; default `configs/critic/prompt.md`.
    prompt_path: str | None = None
    #: Also send each keyframe pair as its own image, besides the comparison sheet.
    send_keyframes: bool = True


class CriticConfig(Section):
    kind: Literal["geometric", "vlm"] = "geometric"
    #: Critique rounds after the IK-only solution (the paper uses 2).
    rounds: int = Field(2, ge=0, le=20)
    #: Which round is the result: `best` = the best fidelity score (landmark-relative location
    #: error plus palm angle, against the human; mean wrist mm to the reference when the body is
    #: unknown), so a revision that made things worse is not kept; `last` = the last revision
    #: (trust the critic's judgement, e.g. a VLM seeing more than the numbers); `auto` = best for
    #: the geometric critic, last for the VLM.
    keep: Literal["auto", "best", "last"] = "auto"
    #: Default primitive amounts when an action names no amount.
    position_step_m: float = Field(0.10, gt=0.0, le=0.5)
    angle_step_deg: float = Field(20.0, gt=0.0, le=90.0)
    #: Largest amount one primitive may carry; larger ones make the whole action invalid.
    max_position_m: float = Field(0.30, gt=0.0, le=1.0)
    max_angle_deg: float = Field(60.0, gt=0.0, le=180.0)
    #: Ramp length at window edges, so windowed offsets do not make the IK targets jump.
    blend_s: float = Field(0.2, ge=0.0, le=5.0)
    #: Geometric critic without the human (no body or robot landmarks): accept when every
    #: side's mean offset / arm length and yaw to the reference are below these. Each one over
    #: its threshold is answered with its primitive (a move, a yaw turn), so a rejection always
    #: proposes something.
    accept_position: float = Field(0.03, gt=0.0, le=1.0)
    accept_yaw_deg: float = Field(8.0, gt=0.0, le=180.0)
    #: Geometric critic against the human (landmark-relative location): accept when every side's
    #: offset from where the human's palm sits, relative to the nearest landmark, is below this
    #: many body scales (shoulder widths; 0.1 ≈ 2.4 cm on G1) and the palm normal is within
    #: `accept_palm_deg`. A hand over either gets at least one primitive for it: a move for the
    #: location, a turn toward the human's palm for the palm (never quantised away).
    accept_location: float = Field(0.1, gt=0.0, le=5.0)
    accept_palm_deg: float = Field(20.0, gt=0.0, le=180.0)
    #: Judge against what the robot can reach (`embody.critic.reach`): the part of a location
    #: offset that would bring a hand closer to the face or chest than the clearance the IK keeps
    #: there (hand-scale chest and face gaps, collision margin), less `reach_slack_m`, is neither asked for
    #: nor counted against acceptance.
    reachable: bool = True
    reach_slack_m: float = Field(0.0, ge=0.0, le=0.1)
    #: Geometric critic: amounts are rounded to these quanta (a VLM speaks in coarse steps too).
    position_quantum_m: float = Field(0.01, gt=0.0, le=0.5)
    angle_quantum_deg: float = Field(5.0, gt=0.0, le=90.0)
    #: Geometric critic: window length for the worst-window search; a window is used when its
    #: offset exceeds the whole-sequence offset by this factor.
    window_s: float = Field(1.0, gt=0.0, le=60.0)
    window_factor: float = Field(2.0, ge=1.0, le=100.0)
    vlm: VLMConfig = VLMConfig()
