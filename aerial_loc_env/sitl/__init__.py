"""ArduPilot SITL in the loop: the bridge's claims (rates, frames, accuracies, follow mode) against a real autopilot.

``process`` finds, checks, starts and kills the SITL binary (``../shared/sitl/`` by default) and notices its death;
``monitor`` reads SITL's SERIAL0 (truth, EKF, events) and commands the vehicle; ``missions`` holds the missions
(the autopilot's parameters, the flight plan over the map) and flies them with the bridge of
``aerial_loc_env.mavlink`` in the loop; ``report`` turns the flight into figures and files; ``cli`` is
``aerial-loc sitl``. Needs the optional extra ``mavlink`` (pymavlink).
"""
