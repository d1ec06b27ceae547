//! Parsing and layering: TOML text to a tree, a layer merged over the tree (only keys the
//! defaults have), a `section.key=value` override applied, the tree deserialised.

use super::ConfigError;

pub(super) fn parse_toml(text: &str, origin: &str) -> Result<toml::Value, ConfigError> {
    text.parse::<toml::Table>()
        .map(toml::Value::Table)
        .map_err(|source| ConfigError::Parse {
            origin: origin.to_string(),
            source: Box::new(source),
        })
}

pub(super) fn deserialize<T: serde::de::DeserializeOwned>(
    tree: toml::Value,
    origin: &str,
) -> Result<T, ConfigError> {
    tree.try_into().map_err(|source| ConfigError::Parse {
        origin: origin.to_string(),
        source: Box::new(source),
    })
}

/// Overlays `user` onto `base`; only keys that exist in the defaults are accepted, so a typo
/// is reported with its full path.
pub(super) fn merge(
    base: &mut toml::Value,
    user: toml::Value,
    prefix: &str,
) -> Result<(), ConfigError> {
    let (toml::Value::Table(base_table), toml::Value::Table(user_table)) = (&mut *base, &user)
    else {
        *base = user;
        return Ok(());
    };
    for (key, value) in user_table.clone() {
        let path = if prefix.is_empty() {
            key.clone()
        } else {
            format!("{prefix}.{key}")
        };
        match base_table.get_mut(&key) {
            Some(slot @ toml::Value::Table(_)) => merge(slot, value, &path)?,
            Some(slot) => *slot = value,
            None => return Err(ConfigError::UnknownKey { key: path }),
        }
    }
    Ok(())
}

pub(super) fn apply_override(tree: &mut toml::Value, item: &str) -> Result<(), ConfigError> {
    let (path, raw) = item
        .split_once('=')
        .ok_or_else(|| ConfigError::OverrideSyntax(item.to_string()))?;
    let path = path.trim();
    if path.is_empty() {
        return Err(ConfigError::OverrideSyntax(item.to_string()));
    }
    // A value is TOML (`0.5`, `true`, `[64, 64]`, `"x"`); a bare word is taken as a string.
    let value = format!("v = {raw}")
        .parse::<toml::Table>()
        .ok()
        .and_then(|mut t| t.remove("v"))
        .unwrap_or_else(|| toml::Value::String(raw.trim().to_string()));
    let mut node = tree;
    let keys: Vec<&str> = path.split('.').collect();
    for (depth, key) in keys.iter().enumerate() {
        let unknown = || ConfigError::UnknownKey {
            key: path.to_string(),
        };
        let table = node.as_table_mut().ok_or_else(unknown)?;
        let child = table.get_mut(*key).ok_or_else(unknown)?;
        if depth + 1 == keys.len() {
            if child.is_table() {
                return Err(ConfigError::Invalid(format!(
                    "{path} is a section; override one of its keys instead"
                )));
            }
            *child = value;
            return Ok(());
        }
        node = child;
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use crate::config::*;

    #[test]
    fn overrides_reach_nested_keys_and_reject_typos() {
        let c = RunConfig::load(
            None,
            &[
                "ppo.learning_rate=1e-3".into(),
                "scenario.intersection.routes=[\"left\"]".into(),
            ],
        )
        .unwrap();
        assert_eq!(c.ppo.learning_rate, 1e-3);
        assert_eq!(c.scenario.intersection.routes, vec![Manoeuvre::Left]);
        let err = RunConfig::load(None, &["ppo.learnin_rate=1".into()]).unwrap_err();
        assert!(matches!(err, ConfigError::UnknownKey { ref key } if key == "ppo.learnin_rate"));
        let bare = RunConfig::load(None, &["learner.device=cpu".into()]).unwrap();
        assert_eq!(bare.learner.device, DeviceChoice::Cpu);
    }

    #[test]
    fn file_layer_rejects_unknown_keys_and_bad_values() {
        let dir = std::env::temp_dir().join(format!("junction-config-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("c.toml");
        std::fs::write(&path, "[ppo]\nclip = 0.2\n[scenario]\nagents = 4\n").unwrap();
        let c = RunConfig::load(Some(&path), &[]).unwrap();
        assert_eq!((c.ppo.clip, c.scenario.agents), (0.2, 4));
        std::fs::write(&path, "[ppo]\nclipp = 0.2\n").unwrap();
        assert!(matches!(
            RunConfig::load(Some(&path), &[]),
            Err(ConfigError::UnknownKey { .. })
        ));
        std::fs::write(&path, "[ppo]\nepochs = 0\n").unwrap();
        assert!(matches!(
            RunConfig::load(Some(&path), &[]),
            Err(ConfigError::Invalid(_))
        ));
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
