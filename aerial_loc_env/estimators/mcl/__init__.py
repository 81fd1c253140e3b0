"""Monte-Carlo localization: the filter loop (``core``), resampling schemes (``resampling``), the odometry motion
model (``motion``), point estimates (``estimate``), the measurement-model plug-in base (``measurement``), the
paper's intensity-pair models (``intensity_pairs``) and the agent (``agent.MCLAgent``); experiments with them run
in the benchmark (``aerial-loc bench``). Modules are imported on use; ``measurement.make_model(name)`` loads the
built-in models."""
