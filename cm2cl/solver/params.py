"""Parameters of the ADMM reconstruction, shared by the device solver and its float64 twin, declared
once: each field of :class:`ADMMParams` carries its validation spec, unit and help, from which the
checks, :func:`cm2cl.reconstruct`'s keywords and documentation and the command line's options are made.

The problem (paper Eq. 4), on the scaled data (see ``normalize``):

    minimise 1/2 ||C H x - y||^2 + l1 ||x||_1 + tv TV_3D(x)   subject to x >= 0

TV_3D(x) = sum sqrt(dx^2 + dy^2 + (axial_weight dz)^2) (isotropic) or
sum |dx| + |dy| + axial_weight |dz| (anisotropic), forward differences, Neumann boundary.
"""

from __future__ import annotations

import inspect
import textwrap
from dataclasses import asdict, dataclass, field, fields

from ..errors import InputError
from ..validate import Checker

#: penalty policies: "adaptive" (default: initial penalties from the problem's scale, then residual
#: balancing with steps sqrt(primal/dual) up to ``adapt_max_step`` on large imbalances), "balance" (the
#: CM2 authors' x``balance_factor`` steps), "fixed" (the initial penalties throughout)
PENALTY_POLICIES = ("adaptive", "balance", "fixed")

#: presets on the accuracy-versus-time front (docs/accuracy_vs_time.md): overrides of the defaults;
#: "balanced" is the default itself
PRESETS = {
    "fast": {"max_iter": 100, "tol": 3e-3, "tol_change": 3e-3, "psf_refine": 0},   # the common round would double it
    "balanced": {},
    "best": {"max_iter": 3000, "tol": 1e-4, "tol_change": 1e-4},
}

#: priors for kinds of samples (``--prior``; docs/quality.md, docs/paper_scenes.md): 'default' (l1 at the
#: universal threshold, plane weights ~ (||h_i|| sum h_i)^(1/2), TV off: on the quality suite the best for beads
#: and fibres alike);
#: 'points' (TV off, each plane's l1 ~ its light: the former prior); 'points-weighted': each plane's l1 weight
#: ~ ||h_i||^2 / sum h_i;
#: 'extended': TV at 5 x the noise level as well, for smooth extended structure, and the PSF refined by one kernel
#: common to every lenslet: kernels per lenslet trade shifts with extended objects (on fibres with every mismatch,
#: the suite's seed and seeds 11, 12, the energy near the truth was 0.26 / 0.16 / 0.12 with 'auto' and
#: 0.41 / 0.38 / 0.38 with 'common'; where 'auto' does not refine per lenslet the two are the same answer;
#: docs/psf_refine.md)
PRIORS = {
    "default": {},
    "points": {"tv_noise_ratio": 0.0, "l1_plane_power": 0.0},
    "points-weighted": {"tv_noise_ratio": 0.0, "l1_plane_power": 2.0},
    "extended": {"tv_noise_ratio": 5.0, "psf_refine": "common"},
}

_NONNEG = {"type": "float", "min": 0}
_POS = {"type": "float", "min": 0, "exclusive": True}
_ITERS = "iterations"


def _param(default, spec: dict, help: str, *, auto: str = "", unit: str = "", flag=None, flag_help: str = ""):
    """A field of :class:`ADMMParams` with its declaration: ``spec`` (the checks), ``help`` (one text for
    the docstring and the command line, ``{name}`` formats a default), ``auto`` (what None means),
    ``unit``, ``flag`` (True: a command-line option named after the field; a string: that option, a bool
    flag that sets the opposite of the default; None: Python only)."""
    return field(default=default, metadata={"spec": spec, "help": help, "auto": auto, "unit": unit, "flag": flag,
                                            "flag_help": flag_help})


@dataclass(frozen=True)
class ADMMParams:
    l1: float | None = _param(
        None, _NONNEG, "Weight of the l1 (sparsity) term on the normalised problem.", flag=True,
        auto="l1_noise_ratio x the volume-domain noise level (the measurement's estimated noise times the RMS "
             "PSF plane norm, info['noise_x']); by default the ratio is the universal threshold sqrt(2 ln N) of "
             "N voxels (info['l1_rule'])")
    tv: float | None = _param(
        None, _NONNEG, "Weight of 3D total variation on the normalised problem; 0 disables TV.", flag=True,
        auto="tv_noise_ratio ({tv_noise_ratio:g}) x the volume-domain noise level")
    # None: the universal threshold (Donoho & Johnstone 1994), chosen on docs/quality.md's suite
    l1_noise_ratio: float | None = _param(
        None, _NONNEG, "Default l1 weight (when l1 is None) relative to the volume-domain noise level.",
        auto="sqrt(2 ln N), N the voxels of the padded volume: the largest back-projected noise of N voxels "
             "stays below it with high probability, so no voxel is lit by noise alone")
    # 0: TV spreads a bead into a plateau where the PSF blurs it; off, fibres are no worse (docs/quality.md)
    tv_noise_ratio: float = _param(
        0.0, _NONNEG, "Default TV weight (when tv is None) relative to the volume-domain noise level.")
    # q = 1 follows noise alone (plane i's back-projected noise is sigma ||h_i||); q = 0 a model error the
    # frame's smooth misfit carries, whose back-projection follows a plane's light, sum h_i (the same in every
    # plane of a stack normalised per plane). Real frames carry both: q = 1/2 passed more of the quality suite's
    # frames on four seeds than either (docs/psf_refine.md, "l1's plane weights"); q = 2 shrinks an isolated
    # voxel alike in every plane. Weights of degree 1 in each plane's scale for every q ("Planes of unequal light")
    l1_plane_power: float = _param(
        0.5, {"type": "float", "min": 0, "max": 4},
        "Plane i's l1 weight is l1 x ||h_i||^q (sum h_i)^(1-q) / mean_j (the same), q this power: 1 makes each "
        "plane's weight follow its back-projected noise sigma ||h_i||; 0 its light (all planes alike where each "
        "holds the same light); 0.5 (default) is halfway, for frames with noise and model error; 2 shrinks a "
        "point source equally in every plane. A plane scaled by a gets a weight a times larger for every q "
        "(info['l1_plane_weights']).", flag=True)
    tv_axial_weight: float = _param(
        1.0, _POS, "Weight of axial differences in TV relative to lateral ones (non-cubic voxels: e.g. dx / dz).",
        flag=True)
    tv_isotropic: bool = _param(True, {"type": "bool"}, "Isotropic (True) or anisotropic (False) TV.",
                                flag="--anisotropic", flag_help="anisotropic TV (default isotropic)")
    tv_iters: int = _param(
        2, {"type": "int", "min": 1, "max": 1000},
        "Chambolle dual iterations of the TV prox per ADMM iteration (warm-started).", unit=_ITERS, flag=True)
    mu_v: float | None = _param(
        None, _POS, "Initial ADMM penalty of the split v = Hx.",
        auto="0.2 on the problem's scale (the data term's curvature is 1 on the ||H|| = 1 scale; 0.2 comes within 1% "
             "of the optimum 2-6x sooner on most cases, docs/penalty.md); 1 in the PSF refinement's rounds, whose "
             "100 iterations shape the volume their kernels are fitted to")
    mu_u: float | None = _param(
        None, _POS, "Initial ADMM penalty of the split u = x (TV).",
        auto="mu_v x the mean of H^T H's spectrum (its maximum is 1)")
    mu_w: float | None = _param(
        None, _POS, "Initial ADMM penalty of the split w = x (l1 and non-negativity).",
        auto="mu_v x the mean of H^T H's spectrum")
    penalty: str = _param(
        "adaptive", {"type": "str", "choices": PENALTY_POLICIES},
        "Penalty policy: 'adaptive' starts from the problem's scale and rebalances a split's penalty by "
        "sqrt(primal / dual residual), bounded by adapt_max_step, when the two differ by more than adapt_ratio "
        "(at iterations adapt_from..10, then every 10th up to adapt_until, within mu_range of the start); "
        "'balance' is the CM2 authors' residual balancing (balance_factor steps when the residuals differ by more "
        "than balance_ratio); 'fixed' keeps the initial penalties.", flag=True)
    balance_factor: float = _param(
        1.1, {"type": "float", "min": 1, "exclusive": True}, "'balance': the factor of one penalty step.")
    balance_ratio: float = _param(
        1.5, {"type": "float", "min": 1}, "'balance': the residual ratio beyond which a penalty steps.")
    # 1000, not 100: early on the duals build up and r / s reads 100-1000 on a fine start (docs/weights.md)
    adapt_ratio: float = _param(
        1000.0, {"type": "float", "min": 1}, "'adaptive': the residual ratio beyond which a penalty is rebalanced.")
    adapt_max_step: float | None = _param(
        None, {"type": "float", "min": 1, "exclusive": True}, "'adaptive': the largest factor of one rebalancing.",
        auto="1.5; 3 in the PSF refinement's rounds")
    adapt_from: int | None = _param(
        None, {"type": "int", "min": 1}, "'adaptive': the first iteration at which penalties are rebalanced.",
        unit=_ITERS,
        auto="10: the residuals of the first iterations are the cold start's transient (docs/iterations.md); 1 from a "
             "start at x0 (a warm start) and in the PSF refinement's rounds, whose 100 iterations shape the volume "
             "their kernels are fitted to")
    # after it the penalties stay, so ADMM's convergence with fixed penalties holds
    adapt_until: int = _param(
        100, {"type": "int", "min": 0}, "'adaptive': the last iteration at which penalties are rebalanced.",
        unit=_ITERS)
    mu_range: float = _param(
        1e4, {"type": "float", "min": 1}, "Penalties stay within [initial / mu_range, initial x mu_range].")
    # 5e-4: at the universal threshold the tail is slower; 1e-3 stopped DiffuserCam 2D / 3D (binned) 2.5% / 3%
    # above the optimum's objective, 5e-4 0.5% / 1.4% (918 / 525 iterations)
    tol: float = _param(
        5e-4, _NONNEG,
        "Stop when every active split's relative primal and dual residuals are below tol (Boyd et al. 2011, "
        "sec. 3.3) and the relative change of x is below tol_change, for patience consecutive iterations; "
        "0 runs to max_iter.", flag=True)
    tol_change: float = _param(5e-4, _NONNEG, "The relative change of x must also be below this to stop.",
                               flag=True)
    patience: int = _param(3, {"type": "int", "min": 1}, "Consecutive iterations the stopping test must hold.",
                           unit=_ITERS, flag=True)
    # 1000: with the background in the model and the universal threshold, solves stop by the rule at
    # ~300-750 iterations (docs/quality.md)
    max_iter: int = _param(1000, {"type": "int", "min": 1}, "Iteration cap.", unit=_ITERS, flag=True)
    # 1.6: iterations to 1% of the converged objective 20-25% fewer on docs/accuracy_vs_time.md's cases
    relaxation: float = _param(
        1.6, {"type": "float", "min": 0, "exclusive": True, "max": 1.95},
        "Over-relaxation alpha of every split (Eckstein & Bertsekas 1992; Boyd et al. 2011, sec. 3.4.3): each prox "
        "and dual update sees alpha H x + (1 - alpha) v_prev instead of H x (alpha x + (1 - alpha) w_prev for the "
        "identity splits); 1 is plain ADMM, 1.5-1.8 usually converges faster, the fixed point is the same.",
        flag=True)
    normalize: bool = _param(
        True, {"type": "bool"}, "Scale y to max 1 and the PSFs to ||H|| = 1 (in float64 on the host; the volume "
        "is scaled back), so that weights and penalties mean the same on every dataset.")
    l1_reweight: int = _param(
        0, {"type": "int", "min": 0, "max": 10},
        "Rounds of reweighted l1 (Candes, Wakin & Boyd 2008): each time the solve converges, each voxel's l1 "
        "weight becomes eps / (x + eps) and the solve goes on, so that strong emitters keep their light and "
        "weak maxima beside them shrink away; 0: plain l1 (the fused fast path).", flag=True)
    l1_reweight_eps: float = _param(
        0.1, {"type": "float", "min": 0, "max": 10, "exclusive": True},
        "eps of the reweighted l1 as a fraction of the volume's maximum.", flag=True)
    # 'auto' by default: rounds of a kernel common to every lenslet removed the ghosts of a blurrier PSF off
    # in depth at about the time of a plain solve, and the view check on that round's volume sends aberrated or
    # vignetted PSFs on to kernels per lenslet (passing mm_aberr and mm_trunc of the quality suite) while matched
    # ones, and the demo's beads between coarse planes, stay at 'common' (docs/psf_refine.md); per-lenslet
    # kernels make an aberrated PSF on fibres worse (they trade shifts with them), so extended volumes get each
    # lenslet's gain alone (docs/psf_refine.md, stop 56)
    psf_refine: int | str = _param(
        "auto", {"type": "int", "min": 0, "max": 20, "words": ("auto", "common")},
        "Rounds of PSF self-calibration (cm2cl.solver.psf_refine): after a solve of psf_refine_iter iterations, "
        "each lenslet's PSF is convolved with a small non-negative kernel fitted to the measurement (its local "
        "blur, shift and gain), and the volume is solved again from the last one; after the rounds the final "
        "solve runs to the stopping rule with the refined PSF (rec.psf, info['psf_refine']). For a PSF that "
        "does not match the sample's optics (aberrations, vignetting, focus); 0: the PSF as given. "
        "'common': two rounds with one kernel common to every lenslet (a blur or a shift of focus of the whole "
        "PSF, interpolated over psf_refine_depth_nodes). 'auto': the first, then a check on its volume: where "
        "the lenslets' views disagree with the PSF (separate kernels per lenslet explain more than 1.5% of the "
        "misfit beyond one common kernel, with an F statistic above 0.6; 2.5% and 1.25 under a camera model's or "
        "a user's unequal pixel weights; info['psf_refine']['check']) and the "
        "volume is made of points (at most half its energy in pieces wider than 3 spots: kernels per lenslet "
        "trade shifts with extended objects) the rest of 12 rounds of kernels per lenslet follow; on an extended "
        "volume 3 rounds fit each lenslet's gain alone (its share of the light: vignetting); where the views "
        "agree the second common round follows (also for a PSF of one view: a diffuser, a single lens). 'auto' and "
        "'common' do not run with padding='support' or lateral tiles (the PSF is then used as given).",
        unit="rounds", flag=True)
    psf_refine_iter: int = _param(
        100, {"type": "int", "min": 1}, "Iterations of each solve before a PSF refinement round.", unit=_ITERS,
        flag=True)
    psf_refine_radius: int = _param(
        3, {"type": "int", "min": 1, "max": 15},
        "Radius of each lenslet's refinement kernel ((2r+1) x (2r+1) taps): the largest blur or shift it models.",
        unit="px", flag=True)
    psf_refine_depth_nodes: int = _param(
        3, {"type": "int", "min": 1, "max": 8},
        "Depth nodes of each lenslet's refinement kernel: the kernel is interpolated linearly between this many "
        "nodes spread evenly over the planes (an aberration that grows with the spot's defocus is no single "
        "convolution); 1: one kernel for every plane.", unit="nodes", flag=True)
    psf_refine_l1_start: float = _param(
        12.0, {"type": "float", "min": 1},
        "The first refinement round solves with this many times the l1 weight, coming down geometrically to 1 x "
        "in the last round: the kernels are first fitted to the brightest structure, before spurious emitters "
        "can absorb the PSF's misfit; 1: every round at the final weight.", unit="x", flag=True)
    # 1: where auto's rounds per lenslet ran, beads the rounds left just below a fifth of the brightest (l1 shrinks
    # every emitter by the same amount, so faint ones lose the largest share) came back (docs/psf_refine.md)
    psf_refine_reweight: int = _param(
        1, {"type": "int", "min": 0, "max": 10},
        "Rounds of reweighted l1 (as l1_reweight, eps 0.3 of the volume's maximum) in the final solve where "
        "psf_refine='auto' fitted kernels per lenslet (the volume is then made of points and the PSF fits each "
        "view): the emitters keep more of their light, which plain l1 shrinks by the same amount for faint and "
        "bright ones alike; 0: plain l1. A given l1_reweight applies instead.", unit="rounds", flag=True)
    # True: frames where the check sends 'auto' to kernels per lenslet also solve the common kernel's answer, and
    # the better fit keeps (docs/psf_refine.md, stop 58: at 200-600 photons the rounds per lenslet lost beads the
    # common kernel found; where the mismatch differs between lenslets they fit the data far better)
    psf_refine_compare: bool = _param(
        True, {"type": "bool"},
        "psf_refine='auto' where the lenslets' views disagree: also solve with the common kernel alone and keep "
        "the answer that fits the data better (info['psf_refine']['compared']); False: kernels per lenslet "
        "without the comparison (about 15% less time on such frames).",
        flag="--no-psf-refine-compare", flag_help="psf_refine auto: kernels per lenslet without solving the common "
        "kernel's answer beside them")
    l1_scale: float = _param(
        1.0, _POS, "Multiplier of the l1 weight, given or by the rule (the PSF refinement's rounds use it).")
    # None: a clear sample; the PSF is a clear-medium calibration (cm2cl.solver.attenuation)
    scattering_length_um: float | str | None = _param(
        None, {**_POS, "words": ("auto",)},
        "Scattering mean free path l_s of the sample: each plane's PSF is scaled by the ballistic fraction "
        "exp(-d / l_s) of its depth d below the surface (surface_um), so that the volume holds the emitters' "
        "brightness before the sample's attenuation (a deep emitter reads as bright as a shallow one); needs the "
        "planes' depths (info['attenuation']). 'auto': l_s estimated from the solved volume, from how its "
        "emitters' light falls with depth (cm2cl.analysis.attenuation: it assumes emitters as bright at every "
        "depth), and each plane divided by its ballistic fraction where the fall is significant "
        "(info['attenuation']['estimate']); a series estimates it once, on frame 0, for every frame.",
        unit="um", flag=True, auto="no attenuation (a clear sample, or a PSF measured in it)")
    surface_um: float | None = _param(
        None, {"type": "float"}, "Depth of the sample's surface, in the planes' depth units (with "
        "scattering_length_um; depth increases with z).", unit="um", flag=True, auto="the shallowest plane")
    background: str = _param(
        "model", {"type": "str", "choices": ("model", "none")},
        "'model': the data term is y = C H x + b with b a smooth, non-negative 2D background estimated jointly "
        "with the volume (cubic B-splines; rec.background), so that haze is not reconstructed as volume; "
        "'none': y = C H x.")
    background_scale_px: float | None = _param(
        None, _POS, "Knot spacing of the background's B-splines in sensor pixels.", unit="px",
        auto="a quarter of the PSF stack's lateral support, at least 8 px")

    def __post_init__(self):
        # the checked values replace the given ones: 2.0 iterations become 2, numpy scalars plain numbers
        for name, value in Checker().fields(self, _SPECS).items():
            object.__setattr__(self, name, value)

    @classmethod
    def from_kwargs(cls, **kw) -> "ADMMParams":
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(kw) - known)
        if unknown:
            raise InputError(f"unknown parameter(s) {unknown}; known: {sorted(known)}")
        return cls(**kw)

    def as_dict(self) -> dict:
        return asdict(self)

    @property
    def tv_step(self) -> float:
        """Step of the projected-gradient TV dual iteration: 1 / ||div||^2 bound."""
        return 1.0 / (4.0 * (2.0 + self.tv_axial_weight ** 2))


#: the fields' validation specs (the Checker's), read from the declaration
_SPECS = {f.name: f.metadata["spec"] for f in fields(ADMMParams)}
_DEFAULTS = {f.name: f.default for f in fields(ADMMParams)}

#: the presets as parameters (checked at import: a preset naming no field, or out of bounds, fails here)
PRESET_PARAMS = {name: ADMMParams(**o) for name, o in PRESETS.items()}


def layered(prior: str | None = None, preset: str | None = None, **given) -> ADMMParams:
    """The parameters of ``prior`` (:data:`PRIORS`), then ``preset`` (:data:`PRESETS`), then the values
    ``given`` that are not None, each layer winning over the one before."""
    for what, name, table in (("prior", prior, PRIORS), ("preset", preset, PRESETS)):
        if name is not None and name not in table:
            raise InputError(f"{what}: unknown {name!r} (known: {', '.join(table)})")
    return ADMMParams.from_kwargs(**{**PRIORS[prior or "default"], **PRESETS[preset or "balanced"],
                                     **{k: v for k, v in given.items() if v is not None}})


@dataclass(frozen=True)
class Param:
    """One parameter as declared: what the docstring and the command line are made from."""
    name: str
    default: object
    type: str            #: the annotation, e.g. 'float | None'
    spec: dict
    help: str            #: with the defaults formatted in
    auto: str            #: what None means ('' when None is not allowed)
    unit: str
    flag: str | None     #: the command-line option, or None
    flag_help: str

    def bounds(self) -> str:
        """The spec's bounds in words: '>= 0', '1 .. 1000', one of choices."""
        s = self.spec
        if "choices" in s:
            return "one of " + ", ".join(repr(c) for c in s["choices"])
        lo, hi = s.get("min"), s.get("max")
        if lo is not None and hi is not None and not s.get("exclusive"):
            return f"{lo:g} .. {hi:g}"
        return ", ".join(t for t in ((f"{'>' if s.get('exclusive') else '>='} {lo:g}" if lo is not None else ""),
                                     (f"<= {hi:g}" if hi is not None else "")) if t)


def parameters() -> list[Param]:
    """The declared parameters, in field order."""
    out = []
    for f in fields(ADMMParams):
        m = f.metadata
        flag = "--" + f.name.replace("_", "-") if m["flag"] is True else m["flag"]
        out.append(Param(f.name, f.default, str(f.type), m["spec"], m["help"].format(**_DEFAULTS),
                         m["auto"].format(**_DEFAULTS), m["unit"], flag, m["flag_help"]))
    return out


def numpydoc(params, indent: int = 4, width: int = 110) -> str:
    """The numpydoc entries of ``params`` for a Parameters section."""
    pad = " " * indent
    lines = []
    for p in params:
        kind = ("{" + ", ".join(repr(c) for c in p.spec["choices"]) + "}" if "choices" in p.spec
                else p.type.replace(" | None", " or None"))
        text = p.help + (f" None (default): {p.auto}." if p.auto else "")
        if p.bounds() and "choices" not in p.spec:
            text += f" Range: {p.bounds()}" + (f" {p.unit}." if p.unit else ".")
        lines.append(f"{pad}{p.name} : {kind}, default {p.default!r}")
        lines.append(textwrap.fill(text, width, initial_indent=pad * 2, subsequent_indent=pad * 2))
    return "\n".join(lines) + "\n"


def with_parameters(doc: str):
    """A decorator: ``func(first, second, *, ..., **params)`` gets the declared parameters as keyword-only
    arguments in its signature (for :func:`inspect.signature` and help()) and ``doc``, with their entries
    at its line ``{parameters}``, as its docstring; the function checks the names it is given with
    :func:`check_keywords`."""
    def decorate(func):
        sig = inspect.signature(func)
        given = [p for p in sig.parameters.values() if p.kind is not inspect.Parameter.VAR_KEYWORD]
        first = [p for p in given if p.kind is not inspect.Parameter.KEYWORD_ONLY]
        declared = [inspect.Parameter(p.name, inspect.Parameter.KEYWORD_ONLY, default=p.default, annotation=p.type)
                    for p in parameters()]
        func.__signature__ = sig.replace(parameters=first + declared + given[len(first):])
        func.__doc__ = doc.replace("    {parameters}\n", numpydoc(parameters()))
        return func
    return decorate


def check_keywords(func_name: str, kw: dict) -> ADMMParams:
    """The parameters of ``kw``; a name that is no parameter is a TypeError, as for a plain function."""
    for name in kw:
        if name not in _SPECS:
            raise TypeError(f"{func_name}() got an unexpected keyword argument {name!r}")
    return ADMMParams(**kw)
