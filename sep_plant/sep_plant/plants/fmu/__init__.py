"""FMU plants: a simulator exported as an FMU (FMI 2.0 or 3.0) as a sep plant (``type: fmu``).

    plant:
      type: fmu
      path: rod.fmu                 # relative to the scenario file
      inputs: [heater_1, heater_2, heater_3]
      outputs: [sensor_1, sensor_2, sensor_3]
      field: T                      # T[1] .. T[n]
      substeps: 4

Modules: `plant` (FMUPlant, its keys), `description` (the modelDescription.xml, checked),
`binding` (one FMU instance, fast C calls), `exchange` (Model Exchange: batched RK4),
`cosim` (Co-Simulation: opaque serialized states), `archive` (SHA-256, the unpacked cache),
`layout` (field coordinates). fmpy is imported only when an FMU is opened. No ROS import.
"""
from sep_plant.plants.fmu.plant import FMUError, FMUPlant

__all__ = ["FMUError", "FMUPlant"]
