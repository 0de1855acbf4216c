"""The simulator: analytic worlds, head motion, device profiles, capture into a recording.

Modules: `world` (scenes), `motion` (head motion), `devices` (device profiles), `config`
(`SimConfig`), `calibration` (true/online/factory), `capture` (`simulate_recording`), `cli`
(`egobench simulate`), `figures`. Imported lazily: ``from egobench.sim.capture import ...``.
"""
