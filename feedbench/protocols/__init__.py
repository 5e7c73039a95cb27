"""Protocol definitions shared by both ends of a link: host drivers and simulated devices.

Frame layouts, register maps and bus helpers live here so that `drivers/` and
`sim_backends/` agree on one definition without importing each other (DESIGN.md).
"""
