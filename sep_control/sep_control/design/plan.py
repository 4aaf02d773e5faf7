"""What a design will cost before it runs: plant run-steps and the largest matrices per stage.

`design_plan` estimates, from the plant's dimensions and the settings only (nothing is run),
the run-steps of each stage (`sep_control.design.runsteps`) and the largest matrix each forms;
`plan_warnings` names the key that drives a cost far above a usual design's (the reference
spends about 1.3e3 run-steps per horizon step with 0.8.0's plan); `log_plan` writes both to
the design log. The counts a design really spent are in its meta's "run_steps".
Pure Python/numpy: no ROS import.
"""
from __future__ import annotations

from typing import Any, Callable

from sep_plant.problem import Problem
from sep_plant.protocol import Plant, noise_channels

from sep_control.design.impulse import SCHEMES, experiment_run_steps, strided_starts
from sep_control.design.noise_sketch import identified_noise_channels
from sep_control.design.runsteps import STAGES
from sep_control.design.spotcheck import SPOT_BLOCKS, SPOT_STARTS
from sep_control.design.stages import PLAN_PQ

#: run-steps per horizon step and per channel above which the plan warns (the reference with
#: 0.8.0's plan: 315k run-steps over N = 250 steps and 5 channels, ~250 per step and channel)
WARN_PER_STEP_CHANNEL = 2500
#: Hankel columns q n_ch above which the plan warns (an SVD of (p n_y) x (q n_ch) per step)
WARN_HANKEL_COLUMNS = 600
#: identifications the mean-only ROM optimizer usually makes (coarse first model, one at the optimum)
USUAL_IDENTIFICATIONS = 2
#: rollouts (one run of N steps each) the mean-only ROM optimizer usually makes: its trial steps
USUAL_ROLLOUTS = 20


def channels(plant: Plant) -> tuple[int, int]:
    """(n_u, n_w): the inputs, and the noise channels identified beside them (0 when the
    process noise enters through the inputs)."""
    n_w = 0 if getattr(plant, "noise_on_inputs", True) else int(noise_channels(plant))
    return int(plant.n_u), n_w


def margin_redesigns(problem: Problem, st) -> int:
    """The passes of the stages the limit-margin loop adds (`pipeline._with_limit_margin`):
    `st.margin_iterations` when the problem limits an input and `st.limit_margin` > 0, else 0."""
    return st.margin_iterations if problem.input_limited and st.limit_margin > 0 else 0


def clip_correction_pass(problem: Problem, st) -> bool:
    """Whether the design may add the clip correction's pass (`pipeline._with_clip_correction`):
    `st.clip_correction` and a problem that limits an input or its rate (the pass runs when the
    ROM predicts that the limits' clipping adds 1 % or more to the closed-loop cost), and no
    limit margin: a margin is the other answer to the same clipping, and a nominal moved inside
    the plain limits would leave the tightened ones the user asked for."""
    return bool(st.clip_correction) and (problem.input_limited or problem.rate_limited) and \
        not margin_redesigns(problem, st)


def design_plan(plant: Plant, problem: Problem, st) -> dict[str, Any]:
    """Estimated run-steps per stage and the largest matrices of a design with settings `st`
    (resolved: `DesignSettings.for_plant`); each pass of the limit-margin loop repeats the
    stages, so it multiplies them; the clip correction may add one pass around a given nominal
    (a rollout, the belief statistics, an identification: counted when it may run)."""
    N, lags = problem.n_steps, st.p + st.q
    n_u, n_w = channels(plant)
    n_ch = n_u + identified_noise_channels(plant, problem.w_std)    # many channels: r_w combinations
    starts = len(strided_starts(N, st.impulse_stride))
    ident = experiment_run_steps(starts, n_ch, lags, st.impulse_scheme) + N + lags
    jac = st.resolved_jacobian_for(plant, N)
    belief = (st.belief_iter + 1) * st.ensemble * N if st.belief else 0
    if st.experiment_plan != "0.8" and st.method == "gn" and jac == "rom":
        steps = _plan_09(st, N, n_u, n_ch, starts, ident)
        steps["belief"] = belief
    else:
        if jac == "rom":
            nominal = USUAL_IDENTIFICATIONS * ident + USUAL_ROLLOUTS * N
        else:
            nominal = 3 * (N * (N + 1) * n_u // 2) + ident
        steps = {"nominal": nominal, "belief": belief, "identification": 0 if jac == "rom" else ident,
                 "validation": 0}
    passes = 1 + margin_redesigns(problem, st)
    steps = {k: passes * v for k, v in steps.items()}
    clip = clip_correction_pass(problem, st)
    if clip:
        extra = {"nominal": N, "belief": st.ensemble * N if st.belief else 0, "identification": ident}
        steps = {k: v + extra.get(k, 0) for k, v in steps.items()}
    matrices = {"hankel": (st.p * int(plant.n_y), st.q * n_ch),
                "field_basis": (int(plant.n_field), None),
                "sensitivity_normal": (N * n_u, N * n_u) if jac == "sensitivity" else None,
                "ensemble": (st.ensemble, int(plant.n_x)) if st.belief else None}
    return {"run_steps": {**steps, "total": sum(steps.values())}, "matrices": matrices, "n_u": n_u, "n_w": n_w,
            "jacobian": jac, "n_w_identified": n_ch - n_u, "passes": passes, "clip_correction": clip}


def _plan_09(st, N: int, n_u: int, n_ch: int, starts: int, ident: int) -> dict[str, int]:
    """Plan 0.9's usual run-steps (`sep_control.design.stages`): a coarse model and one with the
    design's settings, both of the inputs only, and the optimizer's trial rollouts; the design's
    model identified again only when the plant has noise channels beside its inputs (the
    optimizer's models have none), else the optimizer's last one spot-checked at the final input."""
    lags = st.p + st.q
    coarse = 2 * min(st.p, PLAN_PQ) if st.coarse_proposals else lags
    scheme = "forward" if st.coarse_proposals else st.impulse_scheme
    nominal = (experiment_run_steps(starts, n_u, coarse, scheme) + N + coarse
               + experiment_run_steps(starts, n_u, lags, st.impulse_scheme) + N + lags + USUAL_ROLLOUTS * N)
    spot = SPOT_BLOCKS * SPOT_STARTS * (SCHEMES[st.impulse_scheme] * n_ch + (st.impulse_scheme == "forward")) * lags
    noisy = n_ch > n_u
    return {"nominal": nominal, "belief": 0, "identification": ident if noisy else 0,
            "validation": 0 if noisy else spot + N + lags}


def plan_warnings(plan: dict[str, Any], n_steps: int) -> list[str]:
    """Lines naming the key behind a cost far above the usual (none when all is usual)."""
    out = []
    n_ch = plan["n_u"] + plan.get("n_w_identified", plan["n_w"])
    rows, cols = plan["matrices"]["hankel"]
    if cols > WARN_HANKEL_COLUMNS:
        what = (f"{plan['n_w']} process-noise channels identified beside the {plan['n_u']} inputs (the plant's "
                "noise_on_inputs is False, n_w = noise_channels)" if plan["n_w"] else f"q x n_u = {cols}")
        out.append(f"warning: Hankel matrices of {rows} x {cols} per step (an SVD each): {what}; the keys q and "
                   "the plant's noise channels drive it")
    per = plan["run_steps"]["total"] / max(n_steps * max(n_ch, 1), 1)
    if per > WARN_PER_STEP_CHANNEL:
        stage = max(STAGES, key=lambda s: plan["run_steps"].get(s, 0))
        key = {"nominal": "jacobian / max_iter", "belief": "ensemble / belief_iter",
               "identification": "p, q / impulse_scheme"}.get(stage, stage)
        out.append(f"warning: about {plan['run_steps']['total']:.3g} run-steps, {per:.0f} per horizon step and "
                   f"channel (usual: under {WARN_PER_STEP_CHANNEL}); the {stage} stage drives it (keys {key})")
    return out


def format_run_steps(counts: dict[str, int]) -> str:
    """'total T (nominal a, belief b, identification c, ...)' of a run-step count per stage."""
    parts = ", ".join(f"{k} {v:,}" for k, v in counts.items() if k != "total" and v)
    return f"{counts.get('total', 0):,} ({parts})"


def log_plan(plant: Plant, problem: Problem, st, log: Callable[[str], None]) -> dict[str, Any]:
    """Write the plan's estimate and its warnings to `log`; returns the plan."""
    plan = design_plan(plant, problem, st)
    m = plan["matrices"]
    big = [f"{name} {r} x {c}" for name, v in m.items() if v is not None for r, c in [v] if c is not None]
    passes = f", {plan['passes']} passes of the stages (limit margin)" if plan["passes"] > 1 else ""
    if plan.get("clip_correction"):
        passes += ", with the clip correction's pass if the limits clip the feedback"
    log(f"plan ({st.experiment_plan}): about {format_run_steps(plan['run_steps'])} run-steps{passes}; largest matrices: "
        f"{', '.join(big)}; field basis rows {m['field_basis'][0]}")
    for line in plan_warnings(plan, problem.n_steps):
        log(line)
    return plan
