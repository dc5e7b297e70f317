"""What the LP of ``irdrc.core.cmdp`` needs in memory, read before it is built: its transitions'
non-zeros (Σ_a of P_a's, counted from the model's factors, ``ExactMDP.nonzeros``) times the peak
memory per non-zero measured here. An LP past this machine's free memory is refused before any
work (HiGHS would otherwise grow until the system stops the process)."""

from __future__ import annotations

from irdrc.core.checks import grouped
from irdrc.core.params import Params

LP_BYTES_PER_NONZERO = 240
"""The peak memory of a recipe's process per non-zero of the LP's transitions, the largest measured
here on LPs of 3–10 M non-zeros: 112–236 bytes above what the process held before the solve for
the binary modes' LP (``paper`` at 100 and 200 packets, ``multilevel`` at 40, ``large`` at 14), 210
in all for the LP over 21 radar shares."""


def binary_lp_nonzeros(params: Params) -> int:
    """The non-zeros of the binary modes' LP on ``params`` (counted on the factored model, which
    has the dense model's own non-zeros)."""
    from irdrc.core.exact import build_factored

    model = build_factored(params)
    return sum(model.nonzeros(a) for a in range(model.num_actions))


def check_lp_fits(key: str, what: str, nonzeros: int, num_states: int, advice: str) -> None:
    """Refuse an LP whose estimated memory (``LP_BYTES_PER_NONZERO``) is past 80 % of what this
    machine has free: ``key: the LP {what} has … non-zeros for S = … states and would need ~…,
    more than this machine has free (…); {advice}``."""
    from irdrc.recipes.solve import size
    from irdrc.runs.limits import available_memory

    need = LP_BYTES_PER_NONZERO * nonzeros
    free = available_memory()
    if free is not None and need > 0.8 * free:
        raise ValueError(
            f"{key}: the LP {what} has {nonzeros / 1e6:.1f} M non-zeros for S = "
            f"{grouped(num_states)} states and would need ~{size(need)}, more than this machine "
            f"has free ({size(free)}); {advice}"
        )


def check_binary_lp(params: Params, advice: str) -> None:
    """Refuse the binary modes' LP on ``params`` where it would not fit (``check_lp_fits``)."""
    check_lp_fits(
        f"env.queue_capacity={params.env.queue_capacity}",
        f"over {grouped(2 * params.env.num_states)} occupation variables",
        binary_lp_nonzeros(params),
        params.env.num_states,
        advice,
    )
