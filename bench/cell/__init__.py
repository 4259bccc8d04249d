"""A cell's measurement: the service that owns its way (claim, plan, measure, write), the plan,
the runner, its inputs, the freeze check, projectors on disk, packed grafts, job arrays, and the
screen's run that drives the short grafts (screening)."""
