"""Image metrics: PSNR, the standard SSIM and the training loss's 3x3 box SSIM (`image`),
LPIPS-Alex (`lpips`). Plain torch and numpy; they know nothing of Gaussians or runs."""

from sync4d.metrics.image import dssim, psnr, ssim, ssim_gaussian

__all__ = ["dssim", "psnr", "ssim", "ssim_gaussian"]
