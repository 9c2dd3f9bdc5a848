"""The simulated drive's machine: the product's plant physics (:mod:`commission.plant`).

The two-mass + dead-zone model with Coulomb friction, current-loop lag, encoder
quantisation and torque noise lives in the product, so that the tuning's closed-loop
verification and this simulator run one physics; the simulator adds the drive around
it (:mod:`sim_drive.device`). This module names the plant for the simulator's own code.
"""

from commission.plant import Plant, PlantParameters, PlantResponse, PlantSnapshot, PlantState

__all__ = ["Plant", "PlantParameters", "PlantResponse", "PlantSnapshot", "PlantState"]
