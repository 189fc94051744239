"""Measures of images: PSNR and SSIM of the whole frame and of the object's region (`image_fidelity.py`), and LPIPS
loaded offline (`perceptual.py`)."""
