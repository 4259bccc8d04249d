"""Pure functions of stored records: rankings, controls, transfer between backbones, closed loop."""
