"""vigproc: lens vignetting estimation, correction, per-lens profiles and forensics."""
