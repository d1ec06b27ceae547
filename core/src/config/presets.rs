//! Named partial run configurations shipped in `presets/`, compiled in: `--preset NAME`
//! applies one over the defaults, before `--config`, `--scenario` and `--set`. A preset
//! changes how a run is trained, never the task (scene, rewards, episode semantics), so its
//! results compare with the defaults' in what is learned, not in how it is trained.

use super::ConfigError;

/// (name, TOML) of every shipped preset.
pub const SHIPPED: &[(&str, &str)] = &[
    ("fast", include_str!("../../../presets/fast.toml")),
    ("gpu", include_str!("../../../presets/gpu.toml")),
];

/// The TOML of a shipped preset.
pub fn text(name: &str) -> Result<&'static str, ConfigError> {
    SHIPPED
        .iter()
        .find(|(shipped, _)| *shipped == name)
        .map(|(_, text)| *text)
        .ok_or_else(|| ConfigError::UnknownPreset {
            name: name.to_string(),
            known: SHIPPED
                .iter()
                .map(|(name, _)| *name)
                .collect::<Vec<_>>()
                .join(", "),
        })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::config::{Layer, RunConfig};

    #[test]
    fn every_preset_loads_changes_only_training_and_documents_each_key() {
        let defaults = RunConfig::default();
        for (name, text) in SHIPPED {
            let config = RunConfig::from_layers(&[Layer::Preset(name)])
                .unwrap_or_else(|e| panic!("preset {name}: {e}"));
            assert_ne!(config, defaults, "preset {name} changes something");
            assert_eq!(
                config.scenario, defaults.scenario,
                "preset {name} keeps the task"
            );
            let lines: Vec<&str> = text.lines().collect();
            for (i, line) in lines.iter().enumerate() {
                let key = line.trim();
                if key.is_empty() || key.starts_with('#') || key.starts_with('[') {
                    continue;
                }
                assert!(
                    lines[..i]
                        .last()
                        .is_some_and(|l| l.trim_start().starts_with('#')),
                    "preset {name}: {key:?} has no comment above it"
                );
            }
        }
    }

    #[test]
    fn an_unknown_preset_is_refused_with_the_shipped_names() {
        let error = RunConfig::from_layers(&[Layer::Preset("turbo")]).unwrap_err();
        assert_eq!(
            error.to_string(),
            "unknown preset \"turbo\" (shipped presets: fast, gpu)"
        );
    }
}
