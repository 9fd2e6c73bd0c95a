"""Stage 10 — the training losses (paper section II.D, Table 1).

Every photometric term takes per-ray importance weights ``iw`` (DARS ray selection; all ones for uniform
pixels) so each is an unbiased estimate of its uniform-pixel value.

Readings of the paper, documented:

* L_rgb (eq. 25): L1 summed over the three channels, mean over rays.
* L_psnr (eq. 27): the paper *maximises* PSNR; the loss term is −PSNR = 10·log10(MSE).
* L_ssim (eq. 26): 1 − SSIM with the 11 x 11 Gaussian window (σ = 1.5) on rendered patches (reflect padding so a
  16 x 16 patch gives an SSIM value per pixel).
* L_mat (eq. 20): mean squared error of the rendered albedo to ground truth (only where the user enables albedo
  supervision and the scene has it), of roughness to 0.8 on *painting* pixels, and of metallic to
  0.9·1[metal] on labelled pixels (metal → 0.9, other labelled surfaces → 0, as eq. 20 writes it). The paper's
  roughness term ‖r − 0.8·I_paint‖ would also push every non-painting surface to roughness 0; we apply it on
  paintings only.
* L_eikonal (eq. 28): on a density field (σ up to hundreds per metre) ‖∇σ‖ = 1 is not a meaningful target;
  as SPEC allows, we apply the term to the normal head's agreement with −∇σ/‖∇σ‖ (Ref-NeRF's predicted-normal
  loss), weighted by the rendering weights, with ∇σ from central differences.
* L_distortion (eqs. 8, 29): the smoothness of W is a property of the weight maps, which are fixed during field
  training; it is minimised when the maps are built (:func:`toolkit.edges.weight_map` solves for W) and logged
  here as a constant (it carries no gradient to the field).
* Additions not in Table 1: semantic cross-entropy on rendered logits (weight ``semantic``), a small L2 on the
  per-point light residual (``light_reg``), the colour-correction regulariser (``colour_reg``) and mip-NeRF 360's
  interval loss (``compactness``, :func:`compactness_loss` — their "distortion" loss, renamed here so it cannot be
  confused with the paper's L_distortion on W): it pulls each ray's weights into one compact interval, removing
  the semi-transparent fog and floaters an unbounded scene otherwise grows in front of textureless walls. For a
  room (:data:`toolkit.train.config.ROOM_LOSSES`): the sparse-depth loss (:func:`sparse_depth_loss`), the opacity
  loss and the depth-normal loss (:func:`depth_normal_loss`): the rendered normal follows the normal of the rendered
  depth map, so the normal head cannot settle on a direction that merely dims the shading; and the albedo
  smoothness prior (:func:`albedo_smoothness_loss`): where the photo changes smoothly the albedo stays flat, and
  the light's per-point residual takes the change. Off by default for every
  scene: the planarity loss (``planar``, :func:`planarity_loss` on :func:`toolkit.regions.textureless_regions`).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F

from .scene import UNLABELLED

__all__ = ["LossWeights", "rgb_l1", "psnr_loss", "ssim_loss", "material_loss", "semantic_loss",
           "normal_consistency_loss", "depth_normal_loss", "depth_normals", "orientation_loss", "sparse_depth_loss",
           "layout_normal_loss", "planarity_loss",
           "light_residual_loss", "compactness_loss", "albedo_smoothness_loss",
           "PAINTING", "METAL_TARGET", "PAINTING_ROUGHNESS"]

PAINTING = 0
PAINTING_ROUGHNESS = 0.8
METAL_TARGET = 0.9


@dataclass(frozen=True)
class LossWeights:
    """Table 1 weights (paper values as defaults) and our additions."""

    rgb: float = 1.0
    ssim: float = 0.2
    psnr: float = 0.1
    mat: float = 0.5
    eikonal: float | None = None
    """L_eikonal's weight (:func:`normal_consistency_loss`: the normal head follows −∇σ). None = by scene type
    (:data:`toolkit.train.config.EIKONAL`): Table 1's 0.01 for a room, 0.1 for an object, whose normals nothing
    else ties to its shape (README, "Normals that follow an object")."""
    eikonal_start: int = 2000
    """Step after which L_eikonal is active (Table 1: 2000)."""
    eikonal_step: float | None = None
    """The central-difference step of ∇σ in L_eikonal, as a fraction of the scene box's mean edge. None = by scene
    type: 1/512 for a room, 1/64 for an object (at 1/512 an object's −∇σ follows its texture, not its shape)."""
    orientation: float | None = None
    """Ours (Ref-NeRF's orientation loss): penalises normals that face away from the camera. None = by scene type:
    1.0 for a room (``toolkit.train.config.ROOM_LOSSES``), 0.1 for an object (``OBJECT_LOSSES``)."""
    distortion: float = 0.3
    semantic: float = 0.1
    light_reg: float = 0.01
    colour_reg: float = 0.01
    compactness: float = 0.0
    """Ours (mip-NeRF 360's interval loss on contracted-space positions, :func:`compactness_loss`)."""
    opacity: float | None = None
    """Ours: mean (1 − opacity) of the batch's rays — a room is closed, so a ray should end on a surface unless the
    photo shows something no surface can (sky, a lamp): a textureless wall then becomes a surface instead of
    learned environment. None = by scene type (``toolkit.train.config.ROOM_LOSSES`` for rooms, 0 for objects)."""
    depth_normal: float | None = None
    """Ours: the normal head must agree with the normal of the rendered depth map (:func:`depth_normal_loss`, on
    the SSIM patches). 0 = off; None = by scene type, as ``opacity``."""
    sparse_depth: float | None = None
    """Ours (DS-NeRF's idea, our form): rays through the pixels of triangulated sparse points (the photos' own
    features and the poses; :func:`toolkit.bounds.sparse_depth_targets`) must end at the point's depth,
    :func:`sparse_depth_loss`. 0 = off; None = by scene type, as ``opacity``."""
    layout_depth: float | None = None
    """Ours: rays through the pixels of the photos' large textureless regions must end on the room's box
    (:func:`toolkit.layout.fit_room_layout`, a photometric plane sweep over the walls, floor and ceiling), with
    :func:`sparse_depth_loss`; only faces the sweep is confident of give targets. 0 = off; None = by scene type, as
    ``opacity`` (0.1 for a room since 2026-11-29: README, "A room box from the photos")."""
    layout_normal: float | None = None
    """Ours (ManhattanSDF's idea on our own box): the rendered normal of the pixels that ``layout_depth`` sends to
    the room's box must be the inward normal of the face their ray leaves through (a wall's is horizontal, the
    floor's up), :func:`layout_normal_loss`. Nothing here is ground truth: the faces and the pixels come from the
    photometric sweep and the predicted labels. 0 = off; None = by scene type, as ``opacity``."""
    albedo_smooth: float | None = None
    """Ours (Retinex's prior, our form): neighbouring pixels of the SSIM patches whose photo barely changes share one
    albedo (:func:`albedo_smoothness_loss`), so a smooth change of brightness across a wall is left to the light (the
    per-point residual) rather than painted into the albedo. 0 = off; None = by scene type, as ``opacity`` (0.2 for
    a room since 2026-12-06: README, "Albedo that does not follow the light")."""
    planar: float = 0.0
    """Ours (StructNeRF's planar constraint, our form): the rendered points of each large textureless region of a
    photo (:func:`toolkit.regions.textureless_regions`: plain walls, floors) lie on one plane,
    :func:`planarity_loss`. 0 = off, the default for every scene type: at 0.3 it brought the validation galleries'
    walls closer in 6 of 7 paired runs but moved nothing else beyond the seed spread (README, "A planarity prior for
    textureless regions")."""

    @property
    def uses_room_layout(self) -> bool:
        """Whether a term reads the room's box (``layout_depth`` or ``layout_normal`` on): the box is fitted, or
        read from the run or the priors, only then."""
        return (self.layout_depth or 0.0) > 0 or (self.layout_normal or 0.0) > 0


def _wmean(x: torch.Tensor, iw: torch.Tensor | None) -> torch.Tensor:
    if iw is None:
        return x.mean()
    return (x * iw).sum() / iw.sum().clamp_min(1e-12)


def rgb_l1(pred: torch.Tensor, target: torch.Tensor, iw: torch.Tensor | None = None) -> torch.Tensor:
    """Eq. 25: mean over rays of ‖ĉ − c‖₁ (sum over channels). pred/target float [R, 3], iw float [R]."""
    return _wmean((pred - target).abs().sum(-1), iw)


def psnr_loss(pred: torch.Tensor, target: torch.Tensor, iw: torch.Tensor | None = None) -> torch.Tensor:
    """−PSNR = 10·log10(MSE) (eq. 27, maximised). pred/target float [R, 3] in [0, 1]."""
    mse = _wmean((pred - target).square().mean(-1), iw)
    return 10.0 * torch.log10(mse.clamp_min(1e-10))


def ssim_loss(pred_patches: torch.Tensor, target_patches: torch.Tensor, patch_iw: torch.Tensor | None = None) -> torch.Tensor:
    """Eq. 26: 1 − SSIM (11 x 11 Gaussian, σ 1.5, reflect padding) per patch [P, 3, s, s], weighted mean."""
    from .metrics import ssim

    s = ssim(pred_patches, target_patches, window=11, sigma=1.5, padding="reflect")
    return _wmean(1.0 - s, patch_iw)


def material_loss(
    albedo: torch.Tensor | None,
    roughness: torch.Tensor,
    metallic: torch.Tensor,
    labels: torch.Tensor | None,
    metal: torch.Tensor | None,
    albedo_gt: torch.Tensor | None = None,
    iw: torch.Tensor | None = None,
) -> torch.Tensor:
    """Eq. 20 as documented in the module docstring.

    Args:
        albedo: float [R, 3] rendered albedo (for the ground-truth term).
        roughness, metallic: float [R] rendered values.
        labels: int64 [R] class ids (255 unlabelled) or None.
        metal: bool [R] metal-subclass mask or None (then metallic has no target).
        albedo_gt: float [R, 3] ground-truth linear albedo, NaN where unknown, or None.
        iw: float [R] importance weights.
    """
    terms = []
    iw = torch.ones_like(roughness) if iw is None else iw
    if albedo_gt is not None and albedo is not None:
        known = torch.isfinite(albedo_gt).all(-1)
        if known.any():
            err = (albedo - torch.nan_to_num(albedo_gt)).square().mean(-1)
            terms.append((err * iw * known).sum() / (iw * known).sum().clamp_min(1e-12))
    if labels is not None:
        paint = labels == PAINTING
        if paint.any():
            err = (roughness - PAINTING_ROUGHNESS).square()
            terms.append((err * iw * paint).sum() / (iw * paint).sum().clamp_min(1e-12))
        if metal is not None:
            labelled = labels != UNLABELLED
            if labelled.any():
                target = METAL_TARGET * metal.to(metallic.dtype)
                err = (metallic - target).square()
                terms.append((err * iw * labelled).sum() / (iw * labelled).sum().clamp_min(1e-12))
    if not terms:
        return roughness.new_zeros(())
    return torch.stack(terms).sum()


def semantic_loss(logits: torch.Tensor, labels: torch.Tensor, iw: torch.Tensor | None = None) -> torch.Tensor:
    """Cross-entropy of rendered logits [R, C] against labels [R] (255 ignored), importance-weighted."""
    valid = labels != UNLABELLED
    if not valid.any():
        return logits.new_zeros(())
    ce = F.cross_entropy(logits[valid], labels[valid], reduction="none")
    w = None if iw is None else iw[valid]
    return _wmean(ce, w)


def normal_consistency_loss(pred_normals: torch.Tensor, density_gradient: torch.Tensor,
                            weights: torch.Tensor) -> torch.Tensor:
    """Σ w ‖n̂ − (−∇σ/‖∇σ‖)‖² / Σ w over sample points (our L_eikonal, module docstring).

    Args:
        pred_normals: float [M, 3] normal-head outputs (unit).
        density_gradient: float [M, 3] ∇σ at the same points.
        weights: float [M] rendering weights (treated as constants).
    """
    g = -F.normalize(density_gradient, dim=-1, eps=1e-6)
    w = weights.detach()
    return ((pred_normals - g).square().sum(-1) * w).sum() / w.sum().clamp_min(1e-12)


def depth_normals(points: torch.Tensor, view_dirs: torch.Tensor, k: int = 1) -> torch.Tensor:
    """Unit normals of a rendered surface from central differences over ±k pixels, turned toward the camera: the
    target of :func:`depth_normal_loss` (k = 1). Zero where the differences are degenerate.

    Args:
        points: float [..., H, W, 3] surface points of image patches (row-major), H, W ≥ 2k + 1.
        view_dirs: float [..., H, W, 3] ray directions (camera → scene).
        k: half-width of the stencil in pixels (≥ 1).

    Returns:
        float [..., H − 2k, W − 2k, 3] (the interior pixels).
    """
    du = points[..., k:-k, 2 * k:, :] - points[..., k:-k, :-2 * k, :]
    dv = points[..., 2 * k:, k:-k, :] - points[..., :-2 * k, k:-k, :]
    n = F.normalize(torch.cross(du, dv, dim=-1), dim=-1, eps=1e-9)
    return torch.where((n * view_dirs[..., k:-k, k:-k, :]).sum(-1, keepdim=True) > 0, -n, n)


def depth_map_normals(cameras, index: int, depth: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Normals of a whole rendered depth map of camera ``index`` (:func:`depth_normals`, ±1 pixel), and the view's
    ray directions.

    Args:
        cameras: :class:`~toolkit.cameras.Cameras` on ``depth``'s device; ``index`` the view.
        depth: float [H, W] rendered depth along the camera axis.

    Returns:
        (float [H − 2, W − 2, 3] unit normals turned toward the camera (zero where degenerate), float [H, W, 3]
        unit ray directions).
    """
    from .cameras import generate_rays

    h, w = depth.shape
    rays = generate_rays(cameras, [index])
    d = rays.directions.reshape(h, w, 3).float()
    t = depth.float() / rays.z_scale.reshape(h, w).float()  # camera-axis depth -> distance along the ray
    return depth_normals(rays.origins.reshape(h, w, 3).float() + d * t[..., None], d, 1), d


def depth_normal_loss(points: torch.Tensor, normals: torch.Tensor, view_dirs: torch.Tensor,
                      weights: torch.Tensor) -> torch.Tensor:
    """Σ w (1 − n̂ · n_depth) / Σ w over the interior pixels of image patches: the rendered normal n̂ against the
    normal of the surface the rendered depth describes.

    n_depth = normalize(∂P/∂u × ∂P/∂v) from central differences of the patch's rendered surface points P (the ray
    origin plus the expected distance along the ray), turned toward the camera. It is a constant here: the normal
    head follows the geometry, the geometry does not bend toward the head. Unlike −∇σ at single sample points (a
    fog's density gradient points away from the cameras), it sees the surface the photo's pixels agree on.

    Args:
        points: float [P, s, s, 3] rendered surface points of P patches of s x s pixels (row-major, s ≥ 3).
        normals: float [P, s, s, 3] rendered unit normals.
        view_dirs: float [P, s, s, 3] ray directions (camera → scene).
        weights: float [P, s, s] per-pixel weights (e.g. opacity x importance; treated as constants).
    """
    nd = depth_normals(points.detach(), view_dirs, 1)
    ok = (nd.square().sum(-1) > 0.5).to(points.dtype)
    w = weights[:, 1:-1, 1:-1].detach() * ok
    cos = (normals[:, 1:-1, 1:-1] * nd).sum(-1)
    return ((1.0 - cos) * w).sum() / w.sum().clamp_min(1e-12)


def layout_normal_loss(normals: torch.Tensor, targets: torch.Tensor, weights: torch.Tensor) -> torch.Tensor:
    """Σ w (1 − n̂ · n*) / Σ w: rendered normals against known face normals (the room box's, ``losses.layout_normal``).

    Args:
        normals: float [R, 3] rendered normals (normalised here; a zero normal costs 1).
        targets: float [R, 3] unit target normals.
        weights: float [R] per-ray weights, e.g. opacity (treated as constants).
    """
    cos = (F.normalize(normals, dim=-1, eps=1e-6) * targets.to(normals)).sum(-1)
    return _wmean(1.0 - cos, weights.detach())


def orientation_loss(normals: torch.Tensor, view_dirs: torch.Tensor, weights: torch.Tensor) -> torch.Tensor:
    """Σ w max(0, n·d)² / Σ w: a visible surface's normal cannot point away from the camera (Ref-NeRF, eq. 10).

    Without it nothing fixes the normal head's sign before L_eikonal starts, and the photometric loss alone can
    settle on inward normals whose wrong irradiance the albedo and the light residual then absorb.

    Args:
        normals: float [M, 3] unit normals (per sample or per ray).
        view_dirs: float [M, 3] unit ray directions (camera → scene).
        weights: float [M] compositing weights or opacities (treated as constants).
    """
    w = weights.detach()
    back = (normals * view_dirs).sum(-1).clamp_min(0.0)
    return (back.square() * w).sum() / w.sum().clamp_min(1e-12)


def light_residual_loss(residual: torch.Tensor, l_env: torch.Tensor, weights: torch.Tensor) -> torch.Tensor:
    """Σ w ‖Δl‖² / (Σ w · ‖l_env‖²/9): keeps the per-point light a small correction of l_env."""
    w = weights.detach()
    scale = l_env.detach().square().sum() / 9.0 + 1e-6
    return (residual.square().sum((-1, -2)) * w).sum() / (w.sum().clamp_min(1e-12) * scale)


def albedo_smoothness_loss(albedo: torch.Tensor, photo_linear: torch.Tensor, weights: torch.Tensor,
                           sigma: float = 0.1) -> torch.Tensor:
    """Retinex's prior on s x s patches: ``Σ w e^{-(Δ/σ)²} |a_p − a_q|₁ / Σ w`` over horizontally and vertically
    neighbouring pixels p, q, with Δ the largest per-channel change of the photo's log radiance between them. Where
    the photo steps (an edge of a painting, a seam) the pair is free; where it is smooth, the albedo must be too, and
    what brightness change there is must come from the light.

    Args:
        albedo: float [P, s, s, 3] rendered albedo.
        photo_linear: float [P, s, s, 3] the photos' linear radiance at the same pixels.
        weights: float [P, s, s] per-pixel weights (opacity x importance; constants here).
        sigma: the change of log radiance (≈ relative change) at which a pair counts as an edge (e^-1).
    """
    logi = torch.log(photo_linear.detach().clamp_min(1e-3))
    w = weights.detach()
    num = albedo.new_zeros(())
    den = albedo.new_zeros(())
    s = albedo.shape[1]
    for dim in (1, 2):
        step = (logi.narrow(dim, 1, s - 1) - logi.narrow(dim, 0, s - 1)).abs().amax(-1)
        pair = torch.minimum(w.narrow(dim, 1, s - 1), w.narrow(dim, 0, s - 1)) * torch.exp(-(step / sigma) ** 2)
        da = (albedo.narrow(dim, 1, s - 1) - albedo.narrow(dim, 0, s - 1)).abs().mean(-1)
        num = num + (pair * da).sum()
        den = den + pair.sum()
    return num / den.clamp_min(1e-12)


def compactness_loss(weights: torch.Tensor, s_starts: torch.Tensor, s_ends: torch.Tensor, ray_indices: torch.Tensor,
                     n_rays: int) -> torch.Tensor:
    """mip-NeRF 360's interval ("distortion") loss on packed samples, mean over rays:

        Σ_i Σ_j w_i w_j |m_i − m_j| + ⅓ Σ_i w_i² (s_i,end − s_i,start),   m = (s_start + s_end) / 2,

    with s the normalised ray coordinate in [0, 1] (uniform in contracted arc length, :mod:`toolkit.space`). The
    double sum is 2 Σ_i w_i (m_i W_<i − M_<i) with per-ray exclusive prefix sums (samples sorted by ray, then s).

    Args:
        weights: float [S] compositing weights.
        s_starts, s_ends: float [S] interval bounds in normalised ray coordinates.
        ray_indices: int64 [S] sorted ray index of each sample.
        n_rays: R.
    """
    if weights.numel() == 0:
        return weights.new_zeros(())
    mids = 0.5 * (s_starts + s_ends)
    w = weights
    wm = w * mids
    cw = torch.cumsum(w.double(), 0)
    cwm = torch.cumsum(wm.double(), 0)
    counts = torch.bincount(ray_indices, minlength=n_rays)
    first = (torch.cumsum(counts, 0) - counts)[ray_indices]
    base_w = torch.where(first > 0, cw[(first - 1).clamp_min(0)], torch.zeros_like(cw))
    base_wm = torch.where(first > 0, cwm[(first - 1).clamp_min(0)], torch.zeros_like(cwm))
    w_before = (cw - base_w).to(w.dtype) - w  # exclusive
    wm_before = (cwm - base_wm).to(w.dtype) - wm
    inter = 2.0 * (w * (mids * w_before - wm_before)).sum()
    intra = (w.square() * (s_ends - s_starts)).sum() / 3.0
    return (inter + intra) / max(1, n_rays)


def sparse_depth_loss(weights: torch.Tensor, t_samples: torch.Tensor, ray_indices: torch.Tensor, t_target: torch.Tensor,
                      n_rays: int) -> torch.Tensor:
    """Mean over rays of ``Σ_i w_i |t_i − t*| / t* + (1 − Σ_i w_i)``: the ray's weight sits at the known distance
    ``t*`` (relative error, so near and far points count alike) and the ray ends there rather than in the background.

    Unlike a loss on the expected depth, a symmetric fog around ``t*`` is not a minimum: every sample away from ``t*``
    costs its weight times its distance.

    Args:
        weights: float [S] compositing weights of the packed samples.
        t_samples: float [S] distance of each sample along its ray (metres).
        ray_indices: int64 [S] ray of each sample.
        t_target: float [R] known distance along each ray (metres, > 0).
        n_rays: R.
    """
    if n_rays == 0:
        return weights.new_zeros(())
    tt = t_target[ray_indices]
    spread = torch.zeros(n_rays, dtype=weights.dtype, device=weights.device).index_add_(
        0, ray_indices, weights * (t_samples - tt).abs() / tt)
    opacity = torch.zeros(n_rays, dtype=weights.dtype, device=weights.device).index_add_(0, ray_indices, weights)
    return (spread + (1.0 - opacity).clamp_min(0.0)).mean()


def planarity_loss(points: torch.Tensor, weights: torch.Tensor, scale: torch.Tensor) -> torch.Tensor:
    """Mean relative distance of each region's rendered points to the region's best-fitting plane.

    For region k with points X_kj (rendered depth along each ray) and weights a_kj (their rendered opacity), the
    plane is the weighted least-squares fit (centroid c_k, normal n_k = the covariance's smallest eigenvector,
    fitted without gradient: the loss moves the points, not the fit) and the loss is
    ``Σ_kj a_kj |n_k · (X_kj − c_k)| / d_k / Σ_kj a_kj`` with d_k the region's distance from its camera
    (``scale``), so near and far regions count alike.

    Args:
        points: float [K, M, 3] world points (M rays of each of K regions).
        weights: float [K, M] non-negative weights (no gradient is taken through them).
        scale: float [K] > 0, e.g. the mean rendered distance of each region's points (no gradient).
    """
    if points.numel() == 0:
        return points.new_zeros(())
    a = weights.detach().clamp_min(0.0)
    a_sum = a.sum(1, keepdim=True).clamp_min(1e-6)
    c = (a[..., None] * points).sum(1, keepdim=True) / a_sum[..., None]
    with torch.no_grad():
        d = (points - c).detach()
        cov = torch.einsum("km,kmi,kmj->kij", a, d, d) / a_sum[..., None]
        cov = cov + 1e-9 * torch.eye(3, device=cov.device, dtype=cov.dtype)
        n = torch.linalg.eigh(cov.double())[1][..., 0].to(points.dtype)  # eigenvalues ascend: the plane's normal
    dist = ((points - c) * n[:, None, :]).sum(-1).abs() / scale.detach().clamp_min(1e-6)[:, None]
    return (a * dist).sum() / a.sum().clamp_min(1e-6)
