//! What defines a run: [`FitConfig`], saved as the run directory's `config.json` ([`crate::run_dir`]) and
//! versioned ([`FIT_CONFIG_VERSION`]: older files are converted when read), the network it describes, the
//! learning-rate schedule, and the settings in which a resume differs from the saved run.

use dataset::science::brdf::BrdfModel;

use crate::data::{ContextPlanes, StreamConfig};
use crate::model::UNetConfig;

/// The `config.json` format this build writes: version 15 since 2026-12-07 (version 14 lacks `log_coefficients`,
/// which loads as false: a linear output; version 13 also lacks `unit_input`, which
/// loads as false; version 12 also lacks
/// `crater_relief_input`, which loads as false; version 11 also lacks
/// `crater_frame_input`, which loads as false: the crater input is the height alone, and `also_validate_on`, which
/// loads as empty: validation on `--data`'s held-out tiles alone; version 10 also lacks `crater_input`,
/// which loads as false; version 9 also lacks `also_train_on`,
/// which loads as empty: one dataset; version 8 also lacks `weight_decay`, which loads as `None`: plain Adam; version 7 also lacks `nonnegative_start`,
/// which loads as false: the head started at the unconstrained fit; version 6 also lacks `film`, which loads
/// as false; version 5 also lacks `crop_level`, which loads as false; version 4 also lacks `head_hidden`, which loads as 0: the paper's linear head; version 3 also lacks `context_absolute`, which loads as false; version 2 also lacks `steep_weight`, which loads as 1: every crop equally likely). Version 1 (files without a
/// `version` key) added fields one at a time, each absent in older files; those files load with the values
/// every run had before the field existed (constant learning rate, relief input only, no context window). From
/// version 2 on every field is written and required, and a new field means a new version with its conversion
/// in `StoredFitConfig`.
pub const FIT_CONFIG_VERSION: u32 = 15;

/// Everything that defines a run (saved as `config.json`; a resume must match it). The network's head starts
/// at the model's uniform least-squares fit ([`crate::model::UNet::with_uniform_head`]), unconstrained or
/// non-negative (`nonnegative_start`); version-1
/// files also record a `head_init`, which only mattered when their run started and is not read.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(try_from = "StoredFitConfig")]
pub struct FitConfig {
    /// [`FIT_CONFIG_VERSION`]: older files are converted when read.
    pub version: u32,
    pub model: BrdfModel,
    pub epochs: usize,
    pub learning_rate: f64,
    pub base_width: usize,
    pub dropout: bool,
    pub stream: StreamConfig,
    /// Cap on validation samples per epoch (`None` = the whole split).
    pub max_val_samples: Option<usize>,
    /// Learning rate over the run.
    pub lr_schedule: LrSchedule,
    /// Feed absolute elevation as a second input plane ([`crate::data::InputNormalisation`]).
    pub elevation_input: bool,
    /// Feed each sample's wide context window through a context encoder ([`crate::data::InputNormalisation`]).
    pub context_input: bool,
    /// Feed the context window's absolute heights too ([`crate::data::ContextNormalisation::absolute`]); needs
    /// `context_input` and `elevation_input`.
    pub context_absolute: bool,
    /// Feed the crop's height relative to its crater's median profile as a context plane
    /// ([`crate::data::ContextNormalisation::crater_rms_m`]); needs `context_input`.
    pub crater_input: bool,
    /// Feed the crater input as a frame: the height, the normalised radius and whether the crop is framed at all
    /// ([`crate::data::ContextNormalisation::crater_frame`]); needs `crater_input`.
    pub crater_frame_input: bool,
    /// Feed the framing crater's relief over diameter as one more frame plane
    /// ([`crate::data::ContextNormalisation::crater_relief`]); needs `crater_frame_input`.
    pub crater_relief_input: bool,
    /// Feed the context window's highland fraction from a site's unit map, and where it is mapped
    /// ([`crate::data::ContextNormalisation::units`]); needs `context_input`.
    pub unit_input: bool,
    /// Keep an exponential moving average of the weights with this decay ([`crate::weight_average`]), validated and
    /// checkpointed beside the raw network; `None`: no average.
    pub ema_decay: Option<f64>,
    /// How much more often an epoch draws a steep crop than another ([`crate::data::steep_row_weights`]); 1:
    /// every crop equally likely. Above 1 it needs a cap on samples per epoch.
    pub steep_weight: f64,
    /// Channels of the per-pixel hidden layer before the head ([`UNetConfig::head_hidden`]); 0: a linear head.
    pub head_hidden: usize,
    /// The per-crop level branch ([`UNetConfig::crop_level`]); needs `elevation_input`.
    pub crop_level: bool,
    /// The decoder's modulation by the context ([`UNetConfig::film`]); needs `context_input`.
    pub film: bool,
    /// Start the head at the non-negative least-squares uniform fit
    /// ([`crate::uniform_fit::Calibration::model_uniform_nonnegative`]) rather than the unconstrained one.
    pub nonnegative_start: bool,
    /// The network outputs the exponential of its head ([`UNetConfig::log_coefficients`]).
    pub log_coefficients: bool,
    /// Decoupled weight decay (Burn's AdamW): every optimiser step first shrinks each weight by the step's learning
    /// rate times this, then applies the Adam update. `None`: plain Adam, no decay.
    pub weight_decay: Option<f64>,
    /// The dataset names (manifest `name`) of the publications whose train splits were pooled with `--data`'s
    /// ([`crate::data::PooledSource`]), in order; empty: `--data`'s alone. Names, not paths, so a run resumes
    /// from wherever the datasets now lie.
    pub also_train_on: Vec<String>,
    /// The dataset names of the publications whose validation splits were pooled with `--data`'s
    /// ([`crate::data::PooledSource::also_validating_on`]: held-out worlds), in order; empty: `--data`'s alone.
    pub also_validate_on: Vec<String>,
}

/// `config.json` as any version wrote it: the fields version 1 always had, and the later ones as options
/// (`None` = absent from the file; for the nullable fields, a key written as `null` is `Some(None)`).
#[derive(serde::Deserialize)]
struct StoredFitConfig {
    version: Option<u32>,
    model: BrdfModel,
    epochs: usize,
    learning_rate: f64,
    base_width: usize,
    dropout: bool,
    stream: StreamConfig,
    #[serde(default, deserialize_with = "present")]
    max_val_samples: Option<Option<usize>>,
    lr_schedule: Option<LrSchedule>,
    elevation_input: Option<bool>,
    context_input: Option<bool>,
    context_absolute: Option<bool>,
    #[serde(default, deserialize_with = "present")]
    ema_decay: Option<Option<f64>>,
    steep_weight: Option<f64>,
    head_hidden: Option<usize>,
    crop_level: Option<bool>,
    film: Option<bool>,
    nonnegative_start: Option<bool>,
    #[serde(default, deserialize_with = "present")]
    weight_decay: Option<Option<f64>>,
    also_train_on: Option<Vec<String>>,
    crater_input: Option<bool>,
    crater_frame_input: Option<bool>,
    also_validate_on: Option<Vec<String>>,
    crater_relief_input: Option<bool>,
    unit_input: Option<bool>,
    log_coefficients: Option<bool>,
}

/// A key that is in the file, whatever its value (`null` included): serde alone reads a missing `Option` field
/// and a `null` one alike.
fn present<'de, D, T>(deserializer: D) -> Result<Option<Option<T>>, D::Error>
where
    D: serde::Deserializer<'de>,
    T: serde::Deserialize<'de>,
{
    <Option<T> as serde::Deserialize>::deserialize(deserializer).map(Some)
}

impl TryFrom<StoredFitConfig> for FitConfig {
    type Error = String;

    fn try_from(stored: StoredFitConfig) -> Result<Self, String> {
        let version = stored.version.unwrap_or(1);
        let required = |name: &str| {
            format!("config.json version {version} lacks `{name}`: the file was edited or cut short; rewrite it from the run's flags")
        };
        // Every version wrote this one (as `null` when uncapped).
        let max_val_samples = stored
            .max_val_samples
            .ok_or_else(|| required("max_val_samples"))?;
        let (lr_schedule, elevation_input, context_input, ema_decay, steep_weight, context_absolute, head_hidden, crop_level, film, nonnegative_start, weight_decay) = match version {
            // Version 1: a field absent from the file did not exist when its run was written (and `ema_decay`
            // was left out when there was no average).
            1 => (
                stored.lr_schedule.unwrap_or(LrSchedule::Constant),
                stored.elevation_input.unwrap_or(false),
                stored.context_input.unwrap_or(false),
                stored.ema_decay.flatten(),
                1.0,
                false,
                0,
                false,
                false,
                false,
                None,
            ),
            // Versions 2 on write every field they know; version 2 runs drew every crop equally, and runs before
            // version 4 fed relative context heights only.
            2..=FIT_CONFIG_VERSION => (
                stored.lr_schedule.ok_or_else(|| required("lr_schedule"))?,
                stored
                    .elevation_input
                    .ok_or_else(|| required("elevation_input"))?,
                stored.context_input.ok_or_else(|| required("context_input"))?,
                stored.ema_decay.ok_or_else(|| required("ema_decay"))?,
                if version == 2 {
                    1.0
                } else {
                    stored.steep_weight.ok_or_else(|| required("steep_weight"))?
                },
                if version < 4 {
                    false
                } else {
                    stored
                        .context_absolute
                        .ok_or_else(|| required("context_absolute"))?
                },
                if version < 5 {
                    0
                } else {
                    stored.head_hidden.ok_or_else(|| required("head_hidden"))?
                },
                if version < 6 {
                    false
                } else {
                    stored.crop_level.ok_or_else(|| required("crop_level"))?
                },
                if version < 7 {
                    false
                } else {
                    stored.film.ok_or_else(|| required("film"))?
                },
                if version < 8 {
                    false
                } else {
                    stored
                        .nonnegative_start
                        .ok_or_else(|| required("nonnegative_start"))?
                },
                if version < 9 {
                    None
                } else {
                    stored
                        .weight_decay
                        .ok_or_else(|| required("weight_decay"))?
                },
            ),
            newer => {
                return Err(format!(
                    "config.json version {newer} is newer than this g2r-train reads (up to {FIT_CONFIG_VERSION}): update g2r-train"
                ))
            }
        };
        let also_train_on = if version < 10 {
            Vec::new()
        } else {
            stored
                .also_train_on
                .ok_or_else(|| required("also_train_on"))?
        };
        let crater_input = if version < 11 {
            false
        } else {
            stored
                .crater_input
                .ok_or_else(|| required("crater_input"))?
        };
        let (crater_frame_input, also_validate_on) = if version < 12 {
            (false, Vec::new())
        } else {
            (
                stored
                    .crater_frame_input
                    .ok_or_else(|| required("crater_frame_input"))?,
                stored
                    .also_validate_on
                    .ok_or_else(|| required("also_validate_on"))?,
            )
        };
        let crater_relief_input = if version < 13 {
            false
        } else {
            stored
                .crater_relief_input
                .ok_or_else(|| required("crater_relief_input"))?
        };
        let unit_input = if version < 14 {
            false
        } else {
            stored.unit_input.ok_or_else(|| required("unit_input"))?
        };
        let log_coefficients = if version < 15 {
            false
        } else {
            stored
                .log_coefficients
                .ok_or_else(|| required("log_coefficients"))?
        };
        Ok(Self {
            version: FIT_CONFIG_VERSION,
            model: stored.model,
            epochs: stored.epochs,
            learning_rate: stored.learning_rate,
            base_width: stored.base_width,
            dropout: stored.dropout,
            stream: stored.stream,
            max_val_samples,
            lr_schedule,
            elevation_input,
            context_input,
            context_absolute,
            crater_input,
            crater_frame_input,
            crater_relief_input,
            unit_input,
            ema_decay,
            steep_weight,
            head_hidden,
            crop_level,
            film,
            nonnegative_start,
            log_coefficients,
            weight_decay,
            also_train_on,
            also_validate_on,
        })
    }
}

impl FitConfig {
    /// The network this run trains.
    pub fn net_config(&self) -> UNetConfig {
        UNetConfig::new(self.model.param_count())
            .with_in_channels(1 + usize::from(self.elevation_input))
            .with_context_channels(if self.context_input {
                ContextPlanes {
                    absolute: self.context_absolute,
                    crater: self.crater_input,
                    crater_frame: self.crater_frame_input,
                    crater_relief: self.crater_relief_input,
                    units: self.unit_input,
                }
                .count()
            } else {
                0
            })
            .with_base_width(self.base_width)
            .with_dropout(self.dropout)
            .with_head_hidden(self.head_hidden)
            .with_crop_level(self.crop_level)
            .with_film(self.film)
            .with_log_coefficients(self.log_coefficients)
    }

    /// The settings in which `given` differs from `self`, one `name: saved → given` entry each, in name order,
    /// for the resume refusal. Names and values are `config.json`'s (nested names joined by dots); most names are
    /// their flag's with `_` for `-` (`--lr` is `learning_rate`, `--width` is `base_width`).
    pub fn differences(&self, given: &FitConfig) -> Vec<String> {
        fn walk(
            path: &str,
            saved: &serde_json::Value,
            given: &serde_json::Value,
            out: &mut Vec<String>,
        ) {
            match (saved, given) {
                (serde_json::Value::Object(a), serde_json::Value::Object(b)) => {
                    for (key, value) in a {
                        let name = if path.is_empty() {
                            key.clone()
                        } else {
                            format!("{path}.{key}")
                        };
                        walk(
                            &name,
                            value,
                            b.get(key).unwrap_or(&serde_json::Value::Null),
                            out,
                        );
                    }
                }
                _ if saved != given => out.push(format!("{path}: {saved} → {given}")),
                _ => {}
            }
        }
        let as_json =
            |c: &FitConfig| serde_json::to_value(c).expect("a FitConfig serialises to JSON");
        let mut out = Vec::new();
        walk("", &as_json(self), &as_json(given), &mut out);
        // In name order whatever serde_json's map type is.
        out.sort();
        out
    }
}

/// How the learning rate changes over a run's optimiser steps.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum LrSchedule {
    /// `--lr` at every step.
    #[default]
    Constant,
    /// Half a cosine from `--lr` at step 0 to 0 at the last step.
    Cosine,
}

impl LrSchedule {
    /// The rate at optimiser step `step` of `total`.
    pub fn rate(self, base: f64, step: u64, total: u64) -> f64 {
        match self {
            Self::Constant => base,
            Self::Cosine => {
                let t = step.min(total) as f64 / total.max(1) as f64;
                base * 0.5 * (1.0 + (std::f64::consts::PI * t).cos())
            }
        }
    }
}

named_enum!(LrSchedule { Constant => "constant", Cosine => "cosine" });

#[cfg(test)]
mod tests {
    use super::*;
    use crate::data::CONTEXT_CHANNELS;

    #[test]
    fn cosine_decays_from_the_base_rate_to_zero_and_constant_stays() {
        let cosine = LrSchedule::Cosine;
        assert_eq!(cosine.rate(1e-3, 0, 100), 1e-3);
        assert!((cosine.rate(1e-3, 50, 100) - 5e-4).abs() < 1e-15);
        assert!(cosine.rate(1e-3, 100, 100).abs() < 1e-18);
        assert!(cosine.rate(1e-3, 25, 100) > cosine.rate(1e-3, 26, 100));
        assert_eq!(LrSchedule::Constant.rate(1e-3, 77, 100), 1e-3);
    }

    /// The oldest `config.json` layout (version 1, before any optional field).
    const OLDEST: &str = r#"{"model":"m2","epochs":3,"learning_rate":0.001,"base_width":4,"dropout":true,
        "stream":{"seed":42,"batch_size":8,"window_groups":4,"augment":true,"max_samples":null},
        "max_val_samples":null}"#;

    #[test]
    fn version_1_configs_load_with_the_values_runs_had_before_each_field() {
        // The oldest layout, and one with `head_init` (version 1 wrote it; it is not read any more).
        let config: FitConfig = serde_json::from_str(OLDEST).unwrap();
        assert_eq!(config.version, FIT_CONFIG_VERSION);
        assert_eq!(config.lr_schedule, LrSchedule::Constant);
        assert!(!config.elevation_input && !config.context_input);
        assert_eq!(config.ema_decay, None);
        let later = OLDEST.replace(
            r#""max_val_samples":null"#,
            r#""max_val_samples":null,"lr_schedule":"cosine","head_init":"zero","elevation_input":true"#,
        );
        let config: FitConfig = serde_json::from_str(&later).unwrap();
        assert_eq!(config.lr_schedule, LrSchedule::Cosine);
        assert!(config.elevation_input && !config.context_input);
    }

    #[test]
    fn a_resume_refusal_names_exactly_the_settings_that_differ() {
        let saved: FitConfig = serde_json::from_str(OLDEST).unwrap();
        assert!(saved.differences(&saved.clone()).is_empty());
        let mut given = saved.clone();
        given.stream.seed = 43;
        given.also_train_on = vec!["g2r-tycho-full-seed44".into()];
        assert_eq!(
            saved.differences(&given),
            [
                r#"also_train_on: [] → ["g2r-tycho-full-seed44"]"#,
                "stream.seed: 42 → 43"
            ]
        );
    }

    #[test]
    fn current_configs_round_trip_and_require_every_field() {
        let config = FitConfig {
            version: FIT_CONFIG_VERSION,
            model: BrdfModel::L3,
            epochs: 2,
            learning_rate: 3e-4,
            base_width: 8,
            dropout: false,
            stream: StreamConfig {
                seed: 7,
                batch_size: 4,
                window_groups: 2,
                augment: true,
                max_samples: Some(100),
            },
            max_val_samples: Some(16),
            lr_schedule: LrSchedule::Cosine,
            elevation_input: true,
            context_input: true,
            context_absolute: true,
            crater_input: true,
            crater_frame_input: true,
            crater_relief_input: true,
            unit_input: true,
            ema_decay: Some(0.995),
            steep_weight: 3.0,
            head_hidden: 32,
            crop_level: true,
            film: true,
            nonnegative_start: true,
            log_coefficients: true,
            weight_decay: Some(0.01),
            also_train_on: vec!["g2r-tycho-full-seed44".into()],
            also_validate_on: vec!["g2r-many-craters-seed7".into()],
        };
        let json = serde_json::to_string(&config).unwrap();
        assert!(json.contains(r#""version":15"#), "{json}");
        assert_eq!(serde_json::from_str::<FitConfig>(&json).unwrap(), config);
        assert_eq!(config.net_config().context_channels, CONTEXT_CHANNELS + 7);
        assert!(config.net_config().log_coefficients);
        let cut = json.replace(r#","log_coefficients":true"#, "");
        let err = serde_json::from_str::<FitConfig>(&cut)
            .unwrap_err()
            .to_string();
        assert!(err.contains("`log_coefficients`"), "{err}");
        // Version 14 wrote everything but `log_coefficients`: its network's output was linear.
        let v14 = cut.replace(r#""version":15"#, r#""version":14"#);
        let loaded = serde_json::from_str::<FitConfig>(&v14).unwrap();
        assert!(loaded.unit_input && !loaded.log_coefficients);
        assert!(!loaded.net_config().log_coefficients);
        let json = v14;
        let cut = json.replace(r#","unit_input":true"#, "");
        let err = serde_json::from_str::<FitConfig>(&cut)
            .unwrap_err()
            .to_string();
        assert!(err.contains("`unit_input`"), "{err}");
        // Version 13 wrote everything but `unit_input`: its context had no unit planes.
        let v13 = cut.replace(r#""version":14"#, r#""version":13"#);
        let loaded = serde_json::from_str::<FitConfig>(&v13).unwrap();
        assert!(loaded.crater_relief_input && !loaded.unit_input);
        assert_eq!(loaded.net_config().context_channels, CONTEXT_CHANNELS + 5);
        let json = v13;
        let cut = json.replace(r#","context_input":true"#, "");
        let err = serde_json::from_str::<FitConfig>(&cut)
            .unwrap_err()
            .to_string();
        assert!(
            err.contains("version 13") && err.contains("`context_input`"),
            "{err}"
        );
        let cut = json.replace(r#","crater_relief_input":true"#, "");
        let err = serde_json::from_str::<FitConfig>(&cut)
            .unwrap_err()
            .to_string();
        assert!(err.contains("`crater_relief_input`"), "{err}");
        // Version 12 wrote everything but `crater_relief_input`: its frame had no relief plane.
        let v12 = cut.replace(r#""version":13"#, r#""version":12"#);
        let loaded = serde_json::from_str::<FitConfig>(&v12).unwrap();
        assert!(loaded.crater_frame_input && !loaded.crater_relief_input);
        assert_eq!(loaded.net_config().context_channels, CONTEXT_CHANNELS + 4);
        let json = v12;
        let cut = json.replace(r#","crater_frame_input":true"#, "");
        let err = serde_json::from_str::<FitConfig>(&cut)
            .unwrap_err()
            .to_string();
        assert!(err.contains("`crater_frame_input`"), "{err}");
        let cut = cut.replace(r#","also_validate_on":["g2r-many-craters-seed7"]"#, "");
        // Version 11 wrote everything but `crater_frame_input` and `also_validate_on`: its crater input was the
        // height alone, and it validated on one dataset.
        let v11 = cut.replace(r#""version":12"#, r#""version":11"#);
        let loaded = serde_json::from_str::<FitConfig>(&v11).unwrap();
        assert!(loaded.crater_input && !loaded.crater_frame_input);
        assert!(loaded.also_validate_on.is_empty());
        assert_eq!(loaded.net_config().context_channels, CONTEXT_CHANNELS + 2);
        let json = v11;
        let cut = json.replace(r#","crater_input":true"#, "");
        let err = serde_json::from_str::<FitConfig>(&cut)
            .unwrap_err()
            .to_string();
        assert!(err.contains("`crater_input`"), "{err}");
        // Version 10 wrote everything but `crater_input`: its runs fed no crater plane.
        let v10 = cut.replace(r#""version":11"#, r#""version":10"#);
        let loaded = serde_json::from_str::<FitConfig>(&v10).unwrap();
        assert!(!loaded.crater_input && loaded.context_absolute);
        assert_eq!(loaded.net_config().context_channels, CONTEXT_CHANNELS + 1);
        let json = v10;
        let cut = json.replace(r#","also_train_on":["g2r-tycho-full-seed44"]"#, "");
        let err = serde_json::from_str::<FitConfig>(&cut)
            .unwrap_err()
            .to_string();
        assert!(err.contains("`also_train_on`"), "{err}");
        // Version 9 wrote everything but `also_train_on`: its runs trained on one dataset.
        let v9 = cut.replace(r#""version":10"#, r#""version":9"#);
        let loaded = serde_json::from_str::<FitConfig>(&v9).unwrap();
        assert!(loaded.also_train_on.is_empty());
        assert_eq!(loaded.weight_decay, Some(0.01));
        let json = v9;
        // A run without decay writes `null`, which is not a missing key.
        let adam = FitConfig {
            weight_decay: None,
            ..config.clone()
        };
        let adam_json = serde_json::to_string(&adam).unwrap();
        assert!(adam_json.contains(r#""weight_decay":null"#), "{adam_json}");
        assert_eq!(serde_json::from_str::<FitConfig>(&adam_json).unwrap(), adam);
        let cut = json.replace(r#","weight_decay":0.01"#, "");
        let err = serde_json::from_str::<FitConfig>(&cut)
            .unwrap_err()
            .to_string();
        assert!(err.contains("`weight_decay`"), "{err}");
        // Version 8 wrote everything but `weight_decay`: its runs stepped with plain Adam.
        let v8 = cut.replace(r#""version":9"#, r#""version":8"#);
        let loaded = serde_json::from_str::<FitConfig>(&v8).unwrap();
        assert!(loaded.nonnegative_start);
        assert_eq!(loaded.weight_decay, None);
        let json = v8;
        let cut = json.replace(r#","ema_decay":0.995"#, "");
        let err = serde_json::from_str::<FitConfig>(&cut)
            .unwrap_err()
            .to_string();
        assert!(err.contains("`ema_decay`"), "{err}");
        let cut = json.replace(r#","nonnegative_start":true"#, "");
        let err = serde_json::from_str::<FitConfig>(&cut)
            .unwrap_err()
            .to_string();
        assert!(err.contains("`nonnegative_start`"), "{err}");
        // Version 7 wrote everything but `nonnegative_start`: its heads started at the unconstrained fit.
        let v7 = cut.replace(r#""version":8"#, r#""version":7"#);
        let loaded = serde_json::from_str::<FitConfig>(&v7).unwrap();
        assert!(loaded.film && !loaded.nonnegative_start);
        let cut = v7.replace(r#","film":true"#, "");
        let err = serde_json::from_str::<FitConfig>(&cut)
            .unwrap_err()
            .to_string();
        assert!(err.contains("`film`"), "{err}");
        // Version 6 wrote everything but `film`: its runs had no modulated decoder.
        let v6 = cut.replace(r#""version":7"#, r#""version":6"#);
        let loaded = serde_json::from_str::<FitConfig>(&v6).unwrap();
        assert!(loaded.crop_level && !loaded.film);
        let cut = v6.replace(r#","crop_level":true"#, "");
        let err = serde_json::from_str::<FitConfig>(&cut)
            .unwrap_err()
            .to_string();
        assert!(err.contains("`crop_level`"), "{err}");
        // Version 5 wrote everything but `crop_level`: its runs had no level branch.
        let v5 = cut.replace(r#""version":6"#, r#""version":5"#);
        let loaded = serde_json::from_str::<FitConfig>(&v5).unwrap();
        assert_eq!(loaded.head_hidden, 32);
        assert!(!loaded.crop_level);
        let cut = v5.replace(r#","head_hidden":32"#, "");
        let err = serde_json::from_str::<FitConfig>(&cut)
            .unwrap_err()
            .to_string();
        assert!(err.contains("`head_hidden`"), "{err}");
        // Version 4 wrote everything but `head_hidden`: its runs had the paper's linear head.
        let v4 = cut.replace(r#""version":5"#, r#""version":4"#);
        let loaded = serde_json::from_str::<FitConfig>(&v4).unwrap();
        assert!(loaded.context_absolute);
        assert_eq!(loaded.head_hidden, 0);
        let cut = v4.replace(r#","context_absolute":true"#, "");
        let err = serde_json::from_str::<FitConfig>(&cut)
            .unwrap_err()
            .to_string();
        assert!(err.contains("`context_absolute`"), "{err}");
        // Version 3 wrote everything but `context_absolute`: its runs fed relative context heights only.
        let v3 = cut.replace(r#""version":4"#, r#""version":3"#);
        let loaded = serde_json::from_str::<FitConfig>(&v3).unwrap();
        assert!(loaded.context_input && !loaded.context_absolute);
        assert_eq!(loaded.steep_weight, 3.0);
        let cut = v3.replace(r#","steep_weight":3.0"#, "");
        let err = serde_json::from_str::<FitConfig>(&cut)
            .unwrap_err()
            .to_string();
        assert!(err.contains("`steep_weight`"), "{err}");
        // Version 2 wrote everything but `steep_weight`: its runs drew every crop equally.
        let v2 = cut.replace(r#""version":3"#, r#""version":2"#);
        let loaded = serde_json::from_str::<FitConfig>(&v2).unwrap();
        assert_eq!(loaded.steep_weight, 1.0);
        assert!(!loaded.context_absolute);
        assert_eq!(loaded.version, FIT_CONFIG_VERSION);
        let next = FIT_CONFIG_VERSION + 1;
        let newer = serde_json::to_string(&config).unwrap().replace(
            &format!(r#""version":{FIT_CONFIG_VERSION}"#),
            &format!(r#""version":{next}"#),
        );
        let err = serde_json::from_str::<FitConfig>(&newer)
            .unwrap_err()
            .to_string();
        assert!(
            err.contains(&format!("version {next}")) && err.contains("update g2r-train"),
            "{err}"
        );
    }
}
