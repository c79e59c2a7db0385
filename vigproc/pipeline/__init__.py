"""One frame through vigproc: the processor every front end calls, and how failures are classified."""
