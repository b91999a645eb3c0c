"""The paper's case study, a kinematic bicycle on a sine track: its system, env and scene."""
