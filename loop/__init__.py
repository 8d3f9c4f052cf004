"""The closed loop above plant and controller: scenes, in-process simulation, closed-loop analyses and studies, their reports and plots."""
