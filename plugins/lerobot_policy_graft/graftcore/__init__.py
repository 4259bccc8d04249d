"""The graft's torch parts, without LeRobot: the frozen timm encoder (`encoder`) and the wrapper
that turns its grid into a backbone's image tokens (`graft`: pooling, `Projector`, `GraftFeed`).

Shipped in the `lerobot_policy_graft` distribution beside the LeRobot plugin package, which builds
exported policies from them; graftbench imports them from here too (one copy). A package of its own
because importing `lerobot_policy_graft` registers its config types with LeRobot (~4 s of imports
on 2 cores): the harness's start-up check and an xdist controller validate encoder names with
torch and timm alone.
"""
