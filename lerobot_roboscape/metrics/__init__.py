"""Measures of images: PSNR and SSIM of the whole frame and of the object's region, and perceptual distances
(LPIPS, or the tokenizer's features)."""
