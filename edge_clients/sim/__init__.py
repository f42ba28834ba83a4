"""A realistic simulator of a camera network watching people walk: the test bed.

    from edge_clients.sim import SimConfig, Scene, Simulator
    scene = Scene.load("edge_clients/data/ais_lab20")
    sim = Simulator(scene, SimConfig(persons=2, duration=180.0, seed=0))
    for arrival, msg in sim.messages():          # arrival order, bounded memory
        ...
    stats = sim.write("rec.jsonl.gz")            # + ground truth at rec.jsonl.gz.truth.npz
    truth = Truth.load("rec.jsonl.gz.truth.npz")

numpy only (edge sensors run it with the base install). Deterministic: the world
(walkers) derives from ``seed`` alone, each sensor's timing and detector errors from
(seed, sensor name), so one process per sensor produces exactly the messages of the
all-sensor run for that sensor.
"""

from .config import SimConfig
from .scene import Floor, FloorPlan, Scene
from .simulator import Simulator
from .stats import SimStats
from .truth import Truth

__all__ = ["SimConfig", "Scene", "Floor", "FloorPlan", "Simulator", "SimStats", "Truth"]
