"""The covering a field admits from its discs alone (issue 45): the largest uniform one of a
:class:`pipeline.control.fields.FieldAnalysis`, or the one line that says which pair of discs (or disc and target,
or start) makes every covering impossible and by how much. Used by `python -m pipeline.fieldcheck ... write=FILE`
and by the benchmark-like generator :func:`pipeline.control.dense.benchmark_scene`."""

from __future__ import annotations

import numpy as np

from pipeline.control.fields import FieldAnalysis
from pipeline.control.validity import OBSTACLES_FIELD, SQRT2, field_violations
from pipeline.errors import ConfigError


def admitted_covering(ana: FieldAnalysis, margin: float = 0.1) -> tuple[float, float, float]:
    """`(f, g, kappa)`: the largest uniform covering `ana` admits with `margin` of the headroom kept back (the
    bounds are strict): `kappa = sqrt(2) + (1 - margin) (kappa_max - sqrt(2))`, the headroom split evenly between
    the apex `f (r_i + d)` and the reach `g (r_i + d)` (`kappa = f + sqrt(2) g`), the apex also capped by the
    starts. ConfigError (:func:`no_covering`'s line) where the field admits none."""
    if not 0.0 < margin < 1.0:
        raise ConfigError("write_margin", f"the share of the headroom kept back must be in (0, 1), got {margin!r}")
    kappa = SQRT2 + (1.0 - margin) * (ana.kappa_max - SQRT2)
    f = min(SQRT2 + 0.5 * (kappa - SQRT2), SQRT2 + (1.0 - margin) * (ana.start_apex_max - SQRT2))
    return f, (kappa - f) / SQRT2, kappa


def no_covering(centers, cover_radii, target, ana: FieldAnalysis, starts=None) -> ConfigError:
    """The one line of a field no covering admits: what binds (a pair of discs, a disc and the target, a start)
    and by how much (world units); `cover_radii` are `r_i + d`."""
    rr, c = np.asarray(cover_radii, float), np.asarray(centers, float)
    if ana.start_apex_max <= SQRT2 and ana.start_apex.size:
        k, i = np.unravel_index(int(np.argmin(ana.start_apex)), ana.start_apex.shape)
        short = (SQRT2 - ana.start_apex_max) * rr[i]
        return ConfigError(f"init.points[{k}]", f"start {np.round(starts[k], 3).tolist()} lies within the smallest "
                                                f"diamond of {OBSTACLES_FIELD}[{i}] (apex sqrt(2) (r + d)): every "
                                                f"covering contains it; move it {short:.3g} further out")
    field_, cond = ana.kappa_binding
    if cond == "V1":
        i = int(np.argmin(ana.target_kappa))
        short = (SQRT2 - ana.kappa_max) * rr[i]
        return ConfigError(field_, f"the target is {np.hypot(*(np.asarray(target, float) - c[i])):.3g} from this "
                                   f"disc (r + d = {rr[i]:.3g}): every covering holds it (V1 needs more than sqrt(2) "
                                   f"(r + d)); short by {short:.3g}")
    i, j = (int(x) for x in ana.pairs[0])
    need = ana.pair_distance[0] + (SQRT2 - ana.pair_kappa[0]) * (rr[i] + rr[j])
    return ConfigError(field_, f"discs {i} and {j} are {ana.pair_distance[0]:.4g} apart; every covering needs more "
                               f"than {need:.4g} ({cond}: h + 2 u_max T_s + sqrt(2) (r_i + r_j + 2 d)): short by "
                               f"{need - ana.pair_distance[0]:.3g}")


def checked_covering(ana: FieldAnalysis, centers, cover_radii, target, *, margin: float = 0.1, starts=None,
                     **rules) -> tuple[float, float, float]:
    """:func:`admitted_covering`, refused in one line where the field admits none (:func:`no_covering`) or where
    SPEC §3.6's rules (`field_violations` with `rules`: `h`, `u_max`, `T_s`, `arena`) still find a violation of it
    (the analysis and the rules disagree: nothing is built or written)."""
    f, g, kappa = admitted_covering(ana, margin)  # the margin checked first
    if not ana.feasible:
        raise no_covering(centers, cover_radii, target, ana, starts)
    rr = np.asarray(cover_radii, float)
    bad = field_violations(centers, rr, target, apex=f * rr, reach=g * rr, starts=starts, **rules)
    if bad:
        raise ConfigError(bad[0].field, f"the covering apex {f:.4g} (r + d), reach {g:.4g} (r + d) still violates: "
                                        f"{bad[0].message}")
    return f, g, kappa


__all__ = ["admitted_covering", "checked_covering", "no_covering"]
