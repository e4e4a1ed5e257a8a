"""``python -m march.viz terrain|depth|plan``: pictures of the courses, the student's depth image
and the footstep plans."""
