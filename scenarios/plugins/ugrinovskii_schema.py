"""The ``[estimator]`` section of the Ugrinovskii plugin (:mod:`scenarios.plugins.ugrinovskii`):
the disturbances and the biasing attacks of its scenarios."""


from __future__ import annotations

import math
from typing import TYPE_CHECKING, Literal

from pydantic import Field, model_validator

from ..types import Init, Matrix, Strict, ZeroInit

if TYPE_CHECKING:
    pass


Amplitude = float | list[float]


# ============================================================================ schema
class Disturbance(Strict):
    """A disturbance signal: ``zero``; ``white`` (intensity = spectral density of each
    component; held samples of variance ``intensity / dt``); ``pulse`` (``amplitude`` on
    ``[start, start + duration)``, an L2 signal). ``white`` is windowed the same way."""

    kind: Literal["zero", "white", "pulse"] = "zero"
    intensity: float = Field(default=0.0, ge=0)
    amplitude: Amplitude = 0.0
    start: float = Field(default=0.0, ge=0)
    duration: float = Field(default=math.inf, gt=0)

    @model_validator(mode="after")
    def _finite_pulse(self) -> "Disturbance":
        if self.kind == "pulse" and not math.isfinite(self.duration):
            raise ValueError("a pulse needs a finite duration (an L2 signal)")
        return self


class BiasingAttack(Strict):
    """A biasing attack of the admissible class (Definition 1) on node ``node``:
    ``f = f_1 + f_2`` on ``[start, start + duration)``, 0 elsewhere, with the slow biasing
    part ``f_1 = amplitude * min(1, (t - start) / rise)`` (a step when ``rise = 0``) and the
    L2 masking part ``f_2 = masking exp(-(t - start) / masking_decay) cos(masking_omega
    (t - start))`` plus seeded white noise of standard deviation ``masking_noise`` (held
    over each step). ``target = "observer"`` injects ``F_i f`` into (8); ``"detector"``
    injects ``F_c,i f`` into (17) (needs ``detector_attack_matrix = "F"``)."""

    node: int = Field(ge=1, description="1-based agent id")
    target: Literal["observer", "detector"] = "observer"
    start: float = Field(default=0.0, ge=0)
    duration: float = Field(default=math.inf, gt=0)
    amplitude: Amplitude = 0.0
    rise: float = Field(default=0.0, ge=0)
    masking: Amplitude = 0.0
    masking_decay: float = Field(default=1.0, gt=0)
    masking_omega: float = 0.0
    masking_noise: float = Field(default=0.0, ge=0)


class UgrinovskiiEstimator(Strict):
    """Ugrinovskii: controlled distributed H-infinity observers resilient to biasing attacks."""

    algorithm: Literal["ugrinovskii"]
    #: true: observers (8) with the controllers (17)-(19); false: the baseline (8) with u = 0
    controlled: bool = True
    #: how the offline design is made: the LMIs, or footnote 3's closed form (needs gamma2, gamma2_bar)
    method: Literal["lmi", "closed_form"] = "lmi"
    #: relative back-off from the LMI optimum of gamma^2 and gamma_bar^2
    backoff: float = Field(default=0.05, ge=0)
    gamma2: float | None = Field(default=None, gt=0)
    gamma2_bar: float | None = Field(default=None, gt=0)
    #: channel noise in the observer LMI's Ubar: "H" (38) or "H_hat" (reproduces the paper)
    observer_channel: Literal["H", "H_hat"] = "H_hat"
    solver: str = "CLARABEL"
    #: G_i(s) = attack_gain / (s + attack_pole) (Lemma 1), realisation (13) of -G_i(s)/s
    attack_gain: float = Field(default=410.0, gt=0)
    attack_pole: float = Field(default=40.0, gt=0)
    #: F_i, (n, nf) (default [1 ... 1]'); the detector attack matrix F_c,i = 0 or [F_i; 0]
    F: Matrix | None = None
    detector_attack_matrix: Literal["zero", "F"] = "zero"
    #: what neighbours share, W_ij (p x n, default I); channel noise matrices H_ij, H_c,ij
    #: (p x r, default (0.1 / sqrt 2) [1 ... 1]'; H_c defaults to H); Z_ij = Z I, Zbar_ij = Zbar I
    W: Matrix | None = None
    H: Matrix | None = None
    Hc: Matrix | None = None
    Z: float = Field(default=0.01, gt=0)
    Zbar: float = Field(default=0.01, gt=0)
    #: the noise v_ij on c_ij (3) and v_c,ij on eta_ij (18), added by the receiver
    channel_noise: Disturbance = Field(default_factory=Disturbance)
    controller_noise: Disturbance = Field(default_factory=Disturbance)
    biasing: list[BiasingAttack] = Field(default_factory=list)
    #: a node flags an attack when max |u_i| has stayed above threshold for hold seconds
    threshold: float = Field(default=1.0, gt=0)
    hold: float = Field(default=0.05, ge=0)
    #: flags are raised from this time on only (the initial estimation errors move every u_i)
    flag_from: float = Field(default=0.0, ge=0)
    #: initial estimates xi_i (e_hat, eps_hat start at 0)
    x0: Init = Field(default_factory=ZeroInit)
    #: the node re-discretises when a Riccati solution moved by more than this (relative)
    gain_rtol: float = Field(default=1e-3, ge=0)
    #: a .npz (read if it matches, else written) or a run's design.json (read) with the design
    design_cache: str | None = None

    @model_validator(mode="after")
    def _closed_form(self) -> "UgrinovskiiEstimator":
        if self.method == "closed_form" and (self.gamma2 is None or self.gamma2_bar is None):
            raise ValueError("method 'closed_form' needs gamma2 and gamma2_bar")
        if self.method == "lmi" and (self.gamma2 is not None or self.gamma2_bar is not None):
            raise ValueError("gamma2 and gamma2_bar are results of method 'lmi'; give them for method 'closed_form' only")
        return self


