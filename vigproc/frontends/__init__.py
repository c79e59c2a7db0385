"""The front ends: command line, watch-folder daemon, batch jobs, Python API, host hook."""
