"""Monte-Carlo localization: the filter loop (``core``), resampling schemes (``resampling``), the odometry motion
model (``motion``), point estimates (``estimate``), the measurement-model plug-in base (``measurement``), the
paper's intensity-pair models (``intensity_pairs``), the agent (``agent.MCLAgent``) and the experiment script
(``evaluate``). Modules are imported on use; ``measurement.make_model(name)`` loads the built-in models."""
