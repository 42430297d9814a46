"""The paper's metrics (ATE after Sim(3) alignment, PSNR, SSIM, LPIPS when weights exist, depth L1, FPS),
trajectory I/O and paper-style tables."""

from .trajectory import Trajectory, associate, associate_trajectories, format_tum, read_tum, write_tum

__all__ = ["Trajectory", "associate", "associate_trajectories", "format_tum", "read_tum", "write_tum"]
