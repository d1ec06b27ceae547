//! The scenario files shipped in `scenarios/`, compiled in so `--scenario NAME` works from any
//! directory; anything else given to `--scenario` is read as a file path.

use std::path::Path;

use crate::config::{ConfigError, ScenarioConfig};

/// (name, TOML) of every shipped scenario.
pub const SHIPPED: &[(&str, &str)] = &[
    (
        "intersection",
        include_str!("../../scenarios/intersection.toml"),
    ),
    (
        "intersection-metadrive",
        include_str!("../../scenarios/intersection-metadrive.toml"),
    ),
    (
        "roundabout",
        include_str!("../../scenarios/roundabout.toml"),
    ),
    (
        "roundabout-metadrive",
        include_str!("../../scenarios/roundabout-metadrive.toml"),
    ),
    (
        "roundabout-compact-3arm",
        include_str!("../../scenarios/roundabout-compact-3arm.toml"),
    ),
    (
        "roundabout-large-5arm",
        include_str!("../../scenarios/roundabout-large-5arm.toml"),
    ),
    (
        "intersection-on-metadrive",
        include_str!("../../scenarios/intersection-on-metadrive.toml"),
    ),
    (
        "roundabout-on-metadrive",
        include_str!("../../scenarios/roundabout-on-metadrive.toml"),
    ),
    (
        "t-junction",
        include_str!("../../scenarios/t-junction.toml"),
    ),
    (
        "tiny-straight",
        include_str!("../../scenarios/tiny-straight.toml"),
    ),
];

/// A shipped scenario by name, or a scenario TOML file.
pub fn load(name_or_path: &str) -> Result<ScenarioConfig, ConfigError> {
    ScenarioConfig::from_toml(&text(name_or_path)?)
}

/// The TOML of a shipped scenario by name, or of a scenario file.
pub fn text(name_or_path: &str) -> Result<String, ConfigError> {
    if let Some((_, text)) = SHIPPED.iter().find(|(name, _)| *name == name_or_path) {
        return Ok(text.to_string());
    }
    std::fs::read_to_string(Path::new(name_or_path)).map_err(|source| ConfigError::Read {
        path: format!(
            "scenario {name_or_path:?}: neither a shipped scenario ({}) nor a readable file",
            SHIPPED
                .iter()
                .map(|(n, _)| *n)
                .collect::<Vec<_>>()
                .join(", ")
        ),
        source,
    })
}

#[cfg(test)]
mod tests {
    #[test]
    fn every_shipped_scenario_parses_and_names_itself() {
        for (name, _) in super::SHIPPED {
            let scenario = super::load(name).unwrap();
            assert_eq!(
                scenario.name, *name,
                "the file's name key matches its registry name"
            );
        }
        assert!(super::load("no-such-scenario").is_err());
    }
}
