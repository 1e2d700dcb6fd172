//! Exponential moving average of the network's weights (`fit --ema DECAY`).
//!
//! Why: on the small CPU-budget runs the checkpoint that validation picks depends on the seed and on where the
//! last steps happened to land (two of three width-8 seeds picked epoch 0). Averaging the weights over the recent
//! trajectory gives a smoother model from the same steps at no extra training cost; the raw and averaged
//! networks are validated side by side every epoch, so one run measures what averaging buys.
//!
//! The average covers every float tensor of the module, BatchNorm running statistics included (they are state
//! of the averaged network, and averaging them keeps them consistent with its averaged weights).

use burn::module::{Module, ModuleMapper, ModuleVisitor, Param};
use burn::prelude::*;

/// The averaging weight of step `step` (0-based count of updates already applied): `min(decay, (1 + step) /
/// (10 + step))`. The warm-up keeps the first steps (the initialisation) from dominating the average: early on the
/// window is about a ninth of the steps taken, later `1 / (1 - decay)` steps.
pub fn ema_decay_at(decay: f64, step: u64) -> f64 {
    let warm = (1.0 + step as f64) / (10.0 + step as f64);
    decay.min(warm)
}

/// `average ← decay · average + (1 − decay) · current`, parameter by parameter. Both modules must have the same
/// structure (the average starts as a copy of the network it follows).
pub fn ema_update<B: Backend, M: Module<B>>(average: M, current: &M, decay: f64) -> M {
    let mut collect = Collect::<B> {
        tensors: Vec::new(),
    };
    current.visit(&mut collect);
    let mut blend = Blend::<B> {
        current: collect.tensors.into_iter(),
        decay,
    };
    let averaged = average.map(&mut blend);
    assert!(
        blend.current.next().is_none(),
        "averaged network and current network differ in structure"
    );
    averaged
}

/// The current network's float tensors, flattened, in visiting order.
struct Collect<B: Backend> {
    tensors: Vec<Tensor<B, 1>>,
}

impl<B: Backend> ModuleVisitor<B> for Collect<B> {
    fn visit_float<const D: usize>(&mut self, param: &Param<Tensor<B, D>>) {
        let tensor = param.val();
        let n = tensor.shape().num_elements();
        self.tensors.push(tensor.reshape([n]));
    }
}

/// Blends each of the average's float tensors with the current one at the same position (`map` visits fields in
/// the same order as `visit`).
struct Blend<B: Backend> {
    current: std::vec::IntoIter<Tensor<B, 1>>,
    decay: f64,
}

impl<B: Backend> ModuleMapper<B> for Blend<B> {
    fn map_float<const D: usize>(&mut self, param: Param<Tensor<B, D>>) -> Param<Tensor<B, D>> {
        let (id, average, mapper) = param.consume();
        let current = self
            .current
            .next()
            .expect("averaged network has more tensors than the current one");
        assert_eq!(
            current.shape().num_elements(),
            average.shape().num_elements(),
            "averaged and current tensors differ in size"
        );
        let current: Tensor<B, D> = current.reshape(average.shape());
        let blended = average * self.decay + current * (1.0 - self.decay);
        Param::from_mapped_value(id, blended, mapper)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::UNetConfig;
    use burn::backend::Flex;

    /// Every float tensor of a module, BatchNorm running statistics included, in visiting order.
    struct Values(Vec<Vec<f32>>);

    impl ModuleVisitor<Flex> for Values {
        fn visit_float<const D: usize>(&mut self, param: &Param<Tensor<Flex, D>>) {
            self.0
                .push(param.val().into_data().convert::<f32>().to_vec().unwrap());
        }
    }

    fn values<M: Module<Flex>>(module: &M) -> Vec<Vec<f32>> {
        let mut v = Values(Vec::new());
        module.visit(&mut v);
        v.0
    }

    #[test]
    fn an_update_is_the_convex_combination_of_every_tensor() {
        let device = Default::default();
        // Two different networks with a context encoder (every kind of layer the U-Net has).
        let config = UNetConfig::new(3)
            .with_base_width(2)
            .with_in_channels(2)
            .with_context_channels(crate::data::CONTEXT_CHANNELS);
        Flex::seed(&device, 1);
        let average = config.init::<Flex>(&device);
        Flex::seed(&device, 2);
        let current = config.init::<Flex>(&device);
        let (a, c) = (values(&average), values(&current));
        assert!(a.len() > 10 && a != c);
        let blended = values(&ema_update(average, &current, 0.75));
        assert_eq!(blended.len(), a.len());
        for ((b, a), c) in blended.iter().zip(&a).zip(&c) {
            assert_eq!(b.len(), a.len());
            for ((&b, &a), &c) in b.iter().zip(a).zip(c) {
                let want = 0.75 * a + 0.25 * c;
                assert!(
                    (b - want).abs() <= 1e-6 * want.abs().max(1.0),
                    "{b} vs {want}"
                );
            }
        }
    }

    #[test]
    fn the_decay_warms_up_then_holds_at_its_cap() {
        // Step 0 keeps a tenth of the start: the first update mostly takes the network as it is.
        assert!((ema_decay_at(0.995, 0) - 0.1).abs() < 1e-15);
        assert!((ema_decay_at(0.995, 90) - 0.91).abs() < 1e-15);
        assert!(ema_decay_at(0.995, 1000) < 0.995);
        assert_eq!(ema_decay_at(0.995, 10_000), 0.995);
        assert_eq!(ema_decay_at(0.0, 5), 0.0);
    }
}
