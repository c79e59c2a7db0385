"""Forensics: lens consistency, lens identification, crop detection, reports."""
