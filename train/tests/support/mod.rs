//! What the data-parallel tests share: the run they train, and every tensor of a checkpoint by field path.
// Each test crate that includes this module uses a part of it.
#![allow(dead_code)]

use std::path::Path;

use burn::backend::{Autodiff, Flex};
use burn::module::{Module, ModuleVisitor, Param, ParamId};
use burn::prelude::*;
use burn::record::{FullPrecisionSettings, NamedMpkFileRecorder};
use dataset::science::brdf::BrdfModel;
use train::data::StreamConfig;
use train::fit_config::FitConfig;
use train::model::UNet;

pub type Ad = Autodiff<Flex>;
pub type Rec = NamedMpkFileRecorder<FullPrecisionSettings>;

pub mod mpi;

/// Optimiser steps of [`config`]'s epoch.
pub const STEPS: u64 = 4;

pub fn config() -> FitConfig {
    FitConfig {
        version: train::fit_config::FIT_CONFIG_VERSION,
        model: BrdfModel::M2,
        epochs: 1,
        learning_rate: 1e-3,
        base_width: 4,
        dropout: false,
        stream: StreamConfig {
            seed: 5,
            batch_size: 4,
            window_groups: 2,
            augment: true,
            max_samples: Some(4 * STEPS as usize),
        },
        max_val_samples: Some(4),
        lr_schedule: train::fit_config::LrSchedule::Constant,
        elevation_input: false,
        context_input: false,
        ema_decay: Some(0.9),
        steep_weight: 1.0,
        head_hidden: 0,
        crop_level: false,
        film: false,
        nonnegative_start: false,
        log_coefficients: false,
        weight_decay: None,
        also_train_on: Vec::new(),
        also_validate_on: Vec::new(),
        context_absolute: false,
        crater_input: false,
        crater_frame_input: false,
        crater_relief_input: false,
        unit_input: false,
    }
}

/// Every float tensor of a network, by field path, in the order the module lists them.
#[derive(Default)]
pub struct Tensors {
    path: Vec<String>,
    found: Vec<(String, ParamId, Vec<f64>)>,
}

impl<B: Backend> ModuleVisitor<B> for Tensors {
    fn enter_module(&mut self, name: &str, _container_type: &str) {
        self.path.push(name.to_string());
    }
    fn exit_module(&mut self, _name: &str, _container_type: &str) {
        self.path.pop();
    }
    fn visit_float<const D: usize>(&mut self, param: &Param<Tensor<B, D>>) {
        let values = param
            .val()
            .into_data()
            .convert::<f64>()
            .to_vec::<f64>()
            .unwrap();
        self.found.push((self.path.join("."), param.id, values));
    }
}

pub fn tensors<B: Backend>(net: &UNet<B>) -> Vec<(String, ParamId, Vec<f64>)> {
    let mut visitor = Tensors::default();
    net.visit(&mut visitor);
    visitor.found
}

pub fn is_running_stat(path: &str) -> bool {
    path.ends_with("running_mean") || path.ends_with("running_var")
}

pub fn load(run: &Path, cfg: &FitConfig) -> UNet<Flex> {
    let device = Default::default();
    cfg.net_config()
        .init::<Flex>(&device)
        .load_file(run.join("last/model"), &Rec::new(), &device)
        .unwrap()
}

pub fn worst_relative(a: &[f64], b: &[f64]) -> f64 {
    let scale = a.iter().fold(1e-12f64, |m, v| m.max(v.abs()));
    a.iter()
        .zip(b)
        .map(|(x, y)| (x - y).abs())
        .fold(0.0, f64::max)
        / scale
}
