"""Evaluation metrics.

    regions          PSNR over a view's valid pixels, and the paper's central / peripheral split
    color_corrected  psnr_cc and ssim_cc: the prediction's colours fitted to the ground truth first
    perceptual       LPIPS, built only from AlexNet weights already on disk
"""
