"""Image metrics: PSNR and SSIM (`image`), LPIPS-Alex (`lpips`). Plain torch and numpy; they
know nothing of Gaussians or runs."""

from sync4d.metrics.image import dssim, psnr, ssim

__all__ = ["dssim", "psnr", "ssim"]
