"""Configuration: TOML files with the paper's settings as defaults, but for the settings
``paper_differences`` lists.

Every field has a default; an unknown section or key, a value of the wrong type or out of range
(floats must also be finite), is an error that names the file, the section and the key.
``--set section.key=value`` overrides use the same checks. Layers, lowest first: the defaults,
the file's shared sections, its ``[course.<name>.<section>]`` tables for a simulated course
(``load_table_config``), the ``--set`` overrides (``layered_config``). Each setting is declared
once (``setting``); enumerated settings take their allowed values from ``choices``.
"""

from gslam_jax.config.sections import (Config, ConfigError, FilterSection, LocalMapSection,
                                       MapSection, MotionSection, RigSection, StereoSection,
                                       paper_differences)
from gslam_jax.config.toml_files import (apply_overrides, config_to_toml, key_comment,
                                         layered_config, load_config, load_table_config,
                                         parse_config, read_toml, section_to_toml)

__all__ = ["ConfigError", "FilterSection", "MotionSection", "MapSection", "LocalMapSection",
           "StereoSection", "RigSection", "Config", "read_toml", "load_config", "parse_config",
           "apply_overrides", "section_to_toml", "config_to_toml", "key_comment",
           "load_table_config", "layered_config", "paper_differences"]
