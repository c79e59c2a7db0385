"""What vigproc keeps and consults: per-lens profiles, job journals, lensfun and Adobe profile sources."""
