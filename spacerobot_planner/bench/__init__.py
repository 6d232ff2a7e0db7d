"""Benchmarks: `python -m spacerobot_planner.bench {cspace,field,plan,latency,all}`."""
