"""Recordings and viewers other tools open: MCAP with Foxglove's schemas (foxglove-sdk) and Rerun
(rerun-sdk). The `viewers` extra; found by `tensortouch listen --save FILE.mcap|FILE.rrd` through the
`tensortouch.savers` entry points, and by `tensortouch view --rerun`."""
