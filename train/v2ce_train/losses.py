"""The five losses of the V2CE method as the reference implements them (V2CE_SPEC.md section
4), and the Stage 1 metrics of section 6.1 used to pick checkpoints.

Shapes: prediction and ground truth are (B, L, 20, H, W).
"""

import torch
import torch.nn.functional as F

from .model import PatchDiscriminator

# Section 4.8: L = 1000 STP + 1000 TP + 0.5 EF + 1 ADV + 1 BC (TP is weighted by alpha_pyramid).
WEIGHTS = {"stp": 1000.0, "tp": 1000.0, "ef": 0.5, "adv": 1.0, "bc": 1.0}


def _r(x):
    """'b l (p c) h w -> (b p) (l c) h w': (2B, 10L, H, W)."""
    b, l, ch, h, w = x.shape
    return x.view(b, l, 2, ch // 2, h, w).permute(0, 2, 1, 3, 4, 5).reshape(b * 2, l * (ch // 2), h, w)


def _q(x):
    """R(x) as (2B, H*W, 10L)."""
    r = _r(x)
    return r.flatten(2).transpose(1, 2)


def stp(pred, gt):
    """Section 4.1: average pools with cubic kernel = stride 2, 4, 8 over (10L, H, W)."""
    rp, rg = _r(pred).unsqueeze(0), _r(gt).unsqueeze(0)
    total = 0.0
    for s in (2, 4, 8):
        total = total + F.mse_loss(F.avg_pool3d(rp, s), F.avg_pool3d(rg, s))
    return total / 3.0


def tp(pred, gt):
    """Section 4.2: the time axis as it is, pooled by 3 (stride 3, padding 1, zeros counted)
    and by 5; the three MSEs divided by 2, as the reference does."""
    qp, qg = _q(pred), _q(gt)
    t1 = lambda z: F.avg_pool1d(z, 3, 3, 1, count_include_pad=True)  # noqa: E731
    t2 = lambda z: F.avg_pool1d(z, 5, 5)  # noqa: E731
    return (F.mse_loss(qp, qg) + F.mse_loss(t1(qp), t1(qg)) + F.mse_loss(t2(qp), t2(qg))) / 2.0


def ef(pred, gt):
    """Section 4.3, `c+cl` with the split-polarity variant, averaged."""
    b, l, ch, h, w = pred.shape
    ap, ag = pred.abs(), gt.abs()
    ec_p, ec_g = ap.sum(2), ag.sum(2)
    l_ef = 5.0 * F.mse_loss(ec_p, ec_g) + F.mse_loss(ec_p.sum(1), ec_g.sum(1))
    ecp_p = ap.view(b, l, 2, ch // 2, h, w).sum(3)
    ecp_g = ag.view(b, l, 2, ch // 2, h, w).sum(3)
    l_efsp = 2.0 * (5.0 * F.mse_loss(ecp_p, ecp_g) + F.mse_loss(ecp_p.sum(1), ecp_g.sum(1)))
    return (l_ef + l_efsp) / 2.0


def bc(pred, gt):
    """Section 4.5 as implemented: mean of the values above 0.01 per (sample, interval,
    column), reducing channels and rows."""

    def level(x):
        m = (x > 0.01).to(x.dtype)
        return (x * m).sum(dim=(2, 3)) / (m.sum(dim=(2, 3))).clamp(min=1.0)

    return F.mse_loss(level(pred), level(gt))


class Adversarial:
    """Section 4.4: the PatchGAN, updated `k` times per generator step by its own Adam
    (lr 1e-5, betas (0, 0.9), weight decay 1e-5) inside the loss; the generator's term is the
    non-saturating BCE toward "real"."""

    def __init__(self, ndf=64, k=3, device="cpu"):
        self.disc = PatchDiscriminator(20, ndf).to(device)
        self.opt = torch.optim.Adam(
            self.disc.parameters(), lr=1e-5, betas=(0.0, 0.9), eps=1e-8, weight_decay=1e-5
        )
        self.k = k

    def __call__(self, pred, gt):
        b, l, ch, h, w = pred.shape
        fake = pred.reshape(b * l, ch, h, w).float()
        real = gt.reshape(b * l, ch, h, w).float()
        bce = F.binary_cross_entropy_with_logits
        if torch.is_grad_enabled():
            for _ in range(self.k):
                self.opt.zero_grad(set_to_none=True)
                df, dr = self.disc(fake.detach()), self.disc(real)
                loss_d = bce(df, torch.zeros_like(df)) + bce(dr, torch.ones_like(dr))
                loss_d.backward()
                self.opt.step()
            self.opt.zero_grad(set_to_none=True)
        out = self.disc(fake)
        return bce(out, torch.ones_like(out))


def total_loss(pred, gt, adversarial=None):
    """The weighted sum and each term (floats), section 4.8."""
    terms = {"stp": stp(pred, gt), "tp": tp(pred, gt), "ef": ef(pred, gt), "bc": bc(pred, gt)}
    if adversarial is not None:
        terms["adv"] = adversarial(pred, gt)
    total = sum(WEIGHTS[k] * v for k, v in terms.items())
    return total, {k: float(v.detach()) for k, v in terms.items()}


def f1(pred, gt, reduce, threshold=0.01):
    """Section 6.1's micro F1 over every element after `reduce` ('raw', 'sum_c', 'sum_cp'),
    binarised at `threshold`; 0 when neither side has a positive."""
    if reduce == "sum_c":
        b, l, ch, h, w = pred.shape
        pred = pred.view(b, l, 2, ch // 2, h, w).sum(3)
        gt = gt.view(b, l, 2, ch // 2, h, w).sum(3)
    elif reduce == "sum_cp":
        pred, gt = pred.sum(2), gt.sum(2)
    zp, zg = (pred > threshold).float(), (gt > threshold).float()
    tp_ = (zp * zg).sum()
    fp = (zp * (1 - zg)).sum()
    fn = ((1 - zp) * zg).sum()
    prec = tp_ / (tp_ + fp + 1e-8)
    rec = tp_ / (tp_ + fn + 1e-8)
    return float(2 * prec * rec / (prec + rec + 1e-8))
