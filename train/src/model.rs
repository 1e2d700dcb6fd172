//! The U-Net of the paper (docs/design.md, Trainer and evaluation): four down stages (16-32-64-128 at width 16) and a 256 bottleneck, each
//! block two × (conv3×3 → BatchNorm → LeakyReLU) then dropout by depth; max-pool down, nearest ×2 up + conv3×3,
//! skip concatenation, 1×1 head to the BRDF's parameter count. ≈ 2.16 M trainable weights at width 16.
//! `base_width` scales every stage (CPU budgets use 4 or 8; say which).

use burn::nn::conv::{Conv2d, Conv2dConfig};
use burn::nn::pool::{MaxPool2d, MaxPool2dConfig};
use burn::nn::{
    BatchNorm, BatchNormConfig, Dropout, DropoutConfig, Linear, LinearConfig, PaddingConfig2d,
};
use burn::prelude::*;
use burn::tensor::activation::leaky_relu;

use crate::kernels::{
    batch_norm_leaky_relu, conv2d, dropout, join_channels, max_pool2d, pointwise_conv2d_joined,
    upsample_conv2d, TrainOps,
};

/// Negative slope of the network's activations.
const ACTIVATION_SLOPE: f64 = 0.01;
/// Dropout by depth: stages 1-4, then the bottleneck (the up path mirrors the down path).
const DROPOUT_BY_DEPTH: [f64; 5] = [0.0, 0.1, 0.2, 0.3, 0.3];

#[derive(Config, Debug)]
pub struct UNetConfig {
    /// Output channels = the BRDF model's parameter count.
    pub out_channels: usize,
    /// Input planes: relief, plus absolute elevation when the run uses it (`data::InputNormalisation`).
    #[config(default = 1)]
    pub in_channels: usize,
    /// Planes of the context input (`data::CONTEXT_CHANNELS`), or 0 for none: a small encoder turns the
    /// 32 × 32 window into features concatenated, at every position, to the bottleneck's input (where they can
    /// interact with the crop's own terrain) and to the head's (where they reach the parameters directly: through
    /// four up stages a bottleneck change is attenuated 18–41× per stage at initialisation, measured: 3.5e-2 in, 6e-8 out).
    #[config(default = 0)]
    pub context_channels: usize,
    /// Channels of the first stage; the others double per stage.
    #[config(default = 16)]
    pub base_width: usize,
    #[config(default = true)]
    pub dropout: bool,
    /// Channels of a per-pixel hidden layer (1×1 conv → LeakyReLU) between the joined decoder and context
    /// features and the head, or 0 for the paper's linear head. A linear head adds what the crop's own terrain
    /// says to what the context says; a hidden layer lets one gate the other (on a crater wall the same
    /// elevation means another unit than on the plains: docs/crater-diagnosis.md).
    #[config(default = 0)]
    pub head_hidden: usize,
    /// A per-crop level branch: a small MLP from the crop's mean absolute elevation (input plane 1) and the
    /// context features to one offset per output channel, added at every pixel. The convolutional path sees
    /// the elevation through normalised per-pixel features; this branch takes the crop's level as one number
    /// beside what the context says of its surroundings, where a two-input rule (which unit lies under a crater
    /// wall at this height and this place on the crater) is a few units of an MLP.
    #[config(default = false)]
    pub crop_level: bool,
    /// Condition the decoder on the context (feature-wise linear modulation): after every up stage, each channel
    /// is scaled by 1 + γ and shifted by β, where (γ, β) come from a linear map of the context features and, with
    /// an elevation plane, the crop's mean absolute elevation. Joined channels can only add what the context says;
    /// a scale lets the context change how the decoder reads the crop's own terrain (on a crater wall the same
    /// elevation means another unit than on the plains: docs/crater-diagnosis.md). Needs a context input.
    #[config(default = false)]
    pub film: bool,
    /// The head (with the level branch's offset) gives each coefficient's natural logarithm, and the network
    /// outputs its exponential. A linear head adds what the context says (the unit under the crop) to what the
    /// crop's terrain says (a bright fresh wall); albedo factors multiply (composition times maturity times
    /// slope), and in logarithms a sum is a product. With a linear output the unit's step learned on the plains
    /// is too small on a wall half again as bright (docs/experiments.md, forty-first session). Positive
    /// coefficients only: the uniform start must be positive.
    #[config(default = false)]
    pub log_coefficients: bool,
}

/// Hidden units of the crop-level branch ([`UNetConfig::crop_level`]).
const CROP_LEVEL_HIDDEN: usize = 32;

/// The crop-level branch: `[N, 1 + context features]` → `[N, P]`.
#[derive(Module, Debug)]
pub struct CropLevel<B: Backend> {
    hidden: Linear<B>,
    out: Linear<B>,
}

/// The decoder's modulation ([`UNetConfig::film`]): one linear map per up stage, `[N, inputs]` → `[N, 2 C]`
/// (γ then β for the stage's C channels).
#[derive(Module, Debug)]
pub struct Film<B: Backend> {
    stages: Vec<Linear<B>>,
}

#[derive(Module, Debug)]
pub struct ConvBlock<B: Backend> {
    conv1: Conv2d<B>,
    norm1: BatchNorm<B>,
    conv2: Conv2d<B>,
    norm2: BatchNorm<B>,
    dropout: Dropout,
}

fn conv3<B: Backend>(c_in: usize, c_out: usize, device: &B::Device) -> Conv2d<B> {
    Conv2dConfig::new([c_in, c_out], [3, 3])
        .with_padding(PaddingConfig2d::Explicit(1, 1, 1, 1))
        .init(device)
}

impl<B: Backend> ConvBlock<B> {
    fn new(c_in: usize, c_out: usize, dropout: f64, device: &B::Device) -> Self {
        Self {
            conv1: conv3(c_in, c_out, device),
            norm1: BatchNormConfig::new(c_out).init(device),
            conv2: conv3(c_out, c_out, device),
            norm2: BatchNormConfig::new(c_out).init(device),
            dropout: DropoutConfig::new(dropout).init(),
        }
    }

    fn forward(&self, x: Tensor<B, 4>) -> Tensor<B, 4>
    where
        B: TrainOps,
    {
        let x = batch_norm_leaky_relu(&self.norm1, conv2d(&self.conv1, x), ACTIVATION_SLOPE);
        let x = batch_norm_leaky_relu(&self.norm2, conv2d(&self.conv2, x), ACTIVATION_SLOPE);
        dropout(&self.dropout, x)
    }
}

/// The context encoder: three (conv3×3 → BatchNorm → LeakyReLU → max-pool) stages take the 32 × 32 window to
/// 4 × 4, then a linear layer to a feature vector. Flattening (not global pooling) keeps *where* the terrain
/// lies relative to the crop (a rim to the north, a floor underfoot); augmentation turns the window with the crop.
#[derive(Module, Debug)]
pub struct ContextEncoder<B: Backend> {
    convs: Vec<Conv2d<B>>,
    norms: Vec<BatchNorm<B>>,
    linear: Linear<B>,
    pool: MaxPool2d,
}

impl<B: Backend> ContextEncoder<B> {
    fn new(c_in: usize, w: usize, features: usize, device: &B::Device) -> Self {
        let widths = [2 * w, 4 * w, 8 * w];
        let (mut convs, mut norms, mut c) = (Vec::new(), Vec::new(), c_in);
        for &c_out in &widths {
            convs.push(conv3(c, c_out, device));
            norms.push(BatchNormConfig::new(c_out).init(device));
            c = c_out;
        }
        let cells = (dataset::contract::schema::CONTEXT_PX / 8).pow(2);
        Self {
            convs,
            norms,
            linear: LinearConfig::new(c * cells, features).init(device),
            pool: MaxPool2dConfig::new([2, 2]).init(),
        }
    }

    /// `[N, C, 32, 32]` → `[N, features]`.
    fn forward(&self, x: Tensor<B, 4>) -> Tensor<B, 2>
    where
        B: TrainOps,
    {
        let mut x = x;
        for (conv, norm) in self.convs.iter().zip(&self.norms) {
            x = max_pool2d(
                &self.pool,
                batch_norm_leaky_relu(norm, conv2d(conv, x), ACTIVATION_SLOPE),
            );
        }
        let [n, c, h, w] = x.dims();
        leaky_relu(
            self.linear.forward(x.reshape([n, c * h * w])),
            ACTIVATION_SLOPE,
        )
    }
}

#[derive(Module, Debug)]
pub struct UNet<B: Backend> {
    down: Vec<ConvBlock<B>>,
    context: Option<ContextEncoder<B>>,
    bottleneck: ConvBlock<B>,
    up_convs: Vec<Conv2d<B>>,
    up_blocks: Vec<ConvBlock<B>>,
    head_hidden: Option<Conv2d<B>>,
    head: Conv2d<B>,
    level: Option<CropLevel<B>>,
    film: Option<Film<B>>,
    pool: MaxPool2d,
    /// [`UNetConfig::log_coefficients`]. A constant of the module: not in its record, so checkpoints written
    /// before it existed load unchanged, and the run's `config.json` sets it.
    log_coefficients: bool,
}

impl UNetConfig {
    pub fn init<B: Backend>(&self, device: &B::Device) -> UNet<B> {
        let w = self.base_width;
        let widths = [w, 2 * w, 4 * w, 8 * w];
        let p = |depth: usize| {
            if self.dropout {
                DROPOUT_BY_DEPTH[depth]
            } else {
                0.0
            }
        };
        let mut down = Vec::new();
        let mut c_in = self.in_channels;
        for (depth, &c) in widths.iter().enumerate() {
            down.push(ConvBlock::new(c_in, c, p(depth), device));
            c_in = c;
        }
        let context = (self.context_channels > 0).then(|| {
            ContextEncoder::new(self.context_channels, w, self.context_features(), device)
        });
        let bottleneck = ConvBlock::new(c_in + self.context_features(), 16 * w, p(4), device);
        let (mut up_convs, mut up_blocks) = (Vec::new(), Vec::new());
        let mut c_up = 16 * w;
        for (depth, &c) in widths.iter().enumerate().rev() {
            up_convs.push(conv3(c_up, c, device));
            up_blocks.push(ConvBlock::new(2 * c, c, p(depth), device));
            c_up = c;
        }
        let joined = w + self.context_features();
        let head_hidden = (self.head_hidden > 0)
            .then(|| Conv2dConfig::new([joined, self.head_hidden], [1, 1]).init(device));
        let head_in = if self.head_hidden > 0 {
            self.head_hidden
        } else {
            joined
        };
        assert!(
            !self.crop_level || self.in_channels >= 2,
            "the crop-level branch reads the absolute elevation plane (input plane 1)"
        );
        assert!(
            !self.film || self.context_channels > 0,
            "the decoder's modulation reads the context features: the network needs a context input"
        );
        let film_inputs = self.context_features() + usize::from(self.in_channels >= 2);
        let film = self.film.then(|| Film {
            stages: widths
                .iter()
                .rev()
                .map(|&c| LinearConfig::new(film_inputs, 2 * c).init(device))
                .collect(),
        });
        let level = self.crop_level.then(|| CropLevel {
            hidden: LinearConfig::new(1 + self.context_features(), CROP_LEVEL_HIDDEN).init(device),
            out: LinearConfig::new(CROP_LEVEL_HIDDEN, self.out_channels).init(device),
        });
        UNet {
            down,
            context,
            bottleneck,
            up_convs,
            up_blocks,
            head_hidden,
            // Burn's default initialisation, like every other layer: `fit` then starts the head at the uniform fit
            // (`UNet::with_uniform_head`), and a checkpoint replaces it when a trained run is loaded.
            head: Conv2dConfig::new([head_in, self.out_channels], [1, 1]).init(device),
            level,
            film,
            pool: MaxPool2dConfig::new([2, 2]).init(),
            log_coefficients: self.log_coefficients,
        }
    }

    /// BatchNorm running means and variances, which Burn's `num_params` counts but nothing trains.
    pub fn running_stat_count(&self) -> usize {
        let w = self.base_width;
        let block_channels: usize = [w, 2 * w, 4 * w, 8 * w].iter().sum::<usize>() * 2 + 16 * w;
        let context_channels = if self.context_channels > 0 {
            2 * w + 4 * w + 8 * w
        } else {
            0
        };
        // Two BatchNorms per U-Net block and one per context stage, each with a running mean and variance.
        2 * (2 * block_channels + context_channels)
    }

    /// Context features joined to the bottleneck input and to the head (0 without a context input).
    pub fn context_features(&self) -> usize {
        if self.context_channels > 0 {
            4 * self.base_width
        } else {
            0
        }
    }
}

impl<B: Backend> UNet<B> {
    /// Start the head at a uniform model: zero weights and `bias` (raw parameters, one per output channel; their
    /// logarithms with [`UNetConfig::log_coefficients`]), so every pixel's raw parameters are `bias` whatever the
    /// input. `fit` starts here with the model's uniform
    /// least-squares fit: step 0 renders the honest uniform baseline, and training spends its steps on the
    /// spatial variation alone. (Burn's default head made the first renderings O(1) I/F against targets of
    /// ~0.03, and a zero head black ones: the first epochs went on the output's scale; docs/experiments.md.)
    pub fn with_uniform_head(mut self, bias: &[f64], device: &B::Device) -> Self {
        let dims = self.head.weight.dims();
        assert_eq!(bias.len(), dims[0], "one bias per output channel");
        let weight = Tensor::<B, 4>::zeros(dims, device);
        self.head.weight = burn::module::Param::from_tensor(weight);
        let tensor =
            Tensor::<B, 1>::from_data(TensorData::new(bias.to_vec(), [bias.len()]), device);
        self.head.bias = Some(burn::module::Param::from_tensor(tensor));
        // A zero level branch adds nothing: the start stays the uniform fit.
        if let Some(level) = self.level.as_mut() {
            let dims = level.out.weight.dims();
            level.out.weight = burn::module::Param::from_tensor(Tensor::zeros(dims, device));
            level.out.bias = Some(burn::module::Param::from_tensor(Tensor::zeros(
                [dims[1]],
                device,
            )));
        }
        // A zero modulation scales by 1 and shifts by 0: the decoder starts as without it.
        if let Some(film) = self.film.as_mut() {
            for stage in &mut film.stages {
                let dims = stage.weight.dims();
                stage.weight = burn::module::Param::from_tensor(Tensor::zeros(dims, device));
                stage.bias = Some(burn::module::Param::from_tensor(Tensor::zeros(
                    [dims[1]],
                    device,
                )));
            }
        }
        self
    }

    /// `[N, C, 128, 128]` input planes (and `[N, C', 32, 32]` context planes when the network has a context
    /// encoder) → `[N, P, 128, 128]` raw BRDF parameters (the exponential of the head's output with
    /// [`UNetConfig::log_coefficients`]). Panics when `context` does not match the network.
    pub fn forward(&self, x: Tensor<B, 4>, context: Option<Tensor<B, 4>>) -> Tensor<B, 4>
    where
        B: TrainOps,
    {
        let mut skips = Vec::new();
        // The crop's mean absolute elevation, `[N, 1]`, for the level branch and the decoder's modulation.
        let [_, in_channels, _, _] = x.dims();
        let crop_elevation = (self.level.is_some() || (self.film.is_some() && in_channels >= 2))
            .then(|| {
                let [n, _, _, _] = x.dims();
                x.clone()
                    .narrow(1, 1, 1)
                    .mean_dim(3)
                    .mean_dim(2)
                    .reshape([n, 1])
            });
        let mut x = x;
        for block in &self.down {
            let y = block.forward(x);
            x = max_pool2d(&self.pool, y.clone());
            skips.push(y);
        }
        let features = match (&self.context, context) {
            (Some(encoder), Some(context)) => Some(encoder.forward(context)),
            (None, None) => None,
            (encoder, given) => panic!(
                "network has {} context encoder but {} context input was given",
                if encoder.is_some() { "a" } else { "no" },
                if given.is_some() { "a" } else { "no" }
            ),
        };
        // Context features, the same at every position of a `[N, C, h, w]` map, joined as extra channels.
        let join = |x: Tensor<B, 4>| match &features {
            Some(f) => {
                let [n, k] = f.dims();
                let [_, _, h, w] = x.dims();
                let planes = f
                    .clone()
                    .reshape([n, k, 1, 1])
                    .repeat_dim(2, h)
                    .repeat_dim(3, w);
                Tensor::cat(vec![x, planes], 1)
            }
            None => x,
        };
        x = self.bottleneck.forward(join(x));
        // (γ, β) per up stage from the context features and the crop's level.
        let modulation: Vec<Tensor<B, 2>> = match (&self.film, &features) {
            (Some(film), Some(f)) => {
                let inputs = match &crop_elevation {
                    Some(elevation) => Tensor::cat(vec![f.clone(), elevation.clone()], 1),
                    None => f.clone(),
                };
                film.stages
                    .iter()
                    .map(|stage| stage.forward(inputs.clone()))
                    .collect()
            }
            _ => Vec::new(),
        };
        for (stage, (conv, block)) in self.up_convs.iter().zip(&self.up_blocks).enumerate() {
            let skip = skips.pop().expect("one skip per stage");
            let ([_, _, h, w], [_, _, coarse_h, coarse_w]) = (skip.dims(), x.dims());
            // Every stage halves exactly (128 → 8), so nearest ×2 is the interpolation to the skip's size.
            assert!(
                (h, w) == (2 * coarse_h, 2 * coarse_w),
                "up stage {coarse_h}x{coarse_w} -> {h}x{w} is not x2"
            );
            // LeakyReLU(up convolution) joined with the skip, in one pass.
            let up = upsample_conv2d(conv, x);
            x = block.forward(join_channels(up, skip, ACTIVATION_SLOPE));
            if let Some(gamma_beta) = modulation.get(stage) {
                let [n, c, h, w] = x.dims();
                let gamma = gamma_beta.clone().narrow(1, 0, c).reshape([n, c, 1, 1]);
                let beta = gamma_beta.clone().narrow(1, c, c).reshape([n, c, 1, 1]);
                x = x * (gamma.expand([n, c, h, w]) + 1.0) + beta.expand([n, c, h, w]);
            }
        }
        // The 1×1 convolutions that read the joined features at full resolution take them as a per-sample
        // offset, not as planes (`pointwise_conv2d_joined`).
        let joined_conv = |conv: &Conv2d<B>, x: Tensor<B, 4>| match &features {
            Some(f) => pointwise_conv2d_joined(conv, x, f),
            None => conv2d(conv, x),
        };
        let out = match &self.head_hidden {
            Some(hidden) => conv2d(
                &self.head,
                leaky_relu(joined_conv(hidden, x), ACTIVATION_SLOPE),
            ),
            None => joined_conv(&self.head, x),
        };
        let out = match (&self.level, crop_elevation) {
            (Some(level), Some(elevation)) => {
                let inputs = match &features {
                    Some(f) => Tensor::cat(vec![elevation, f.clone()], 1),
                    None => elevation,
                };
                let offset = level
                    .out
                    .forward(leaky_relu(level.hidden.forward(inputs), ACTIVATION_SLOPE));
                let [n, p, h, w] = out.dims();
                out + offset.reshape([n, p, 1, 1]).expand([n, p, h, w])
            }
            _ => out,
        };
        if self.log_coefficients {
            out.exp()
        } else {
            out
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use burn::backend::{Autodiff, Flex};
    use burn::tensor::Distribution;

    type Ad = Autodiff<Flex>;

    /// The modulation starts at no change (a zero map scales by 1 and shifts by 0), yet it trains: the loss's
    /// gradient reaches its weights.
    #[test]
    fn the_decoder_modulation_starts_as_identity_and_receives_gradients() {
        let device = Default::default();
        let config = UNetConfig::new(1)
            .with_in_channels(2)
            .with_context_channels(2)
            .with_base_width(4)
            .with_dropout(false);
        let x = Tensor::<Ad, 4>::random([2, 2, 128, 128], Distribution::Normal(0.0, 1.0), &device);
        let context =
            Tensor::<Ad, 4>::random([2, 2, 32, 32], Distribution::Normal(0.0, 1.0), &device);
        // A uniform head would hide the decoder: read its features through a head of ones.
        let mut modulated = config
            .with_film(true)
            .init::<Ad>(&device)
            .with_uniform_head(&[0.1], &device);
        let dims = modulated.head.weight.dims();
        modulated.head.weight = burn::module::Param::from_tensor(Tensor::ones(dims, &device));
        let b = modulated.forward(x.clone(), Some(context.clone()));
        // The same network without the modulation (cloned after the forward pass: Burn initialises parameters
        // lazily, on first use, and a clone taken before would draw its own).
        let mut plain = modulated.clone();
        plain.film = None;
        let a = plain.forward(x, Some(context));
        let worst = (a - b.clone()).abs().max().into_scalar();
        assert_eq!(
            worst, 0.0,
            "a zero modulation changed the output by {worst}"
        );

        let grads = b.powi_scalar(2).mean().backward();
        let film = modulated.film.as_ref().expect("modulated");
        let moved: f32 = film
            .stages
            .iter()
            .map(|stage| {
                stage
                    .weight
                    .grad(&grads)
                    .expect("a gradient")
                    .abs()
                    .sum()
                    .into_scalar()
            })
            .sum();
        assert!(moved > 0.0, "no gradient reached the modulation");
    }

    /// With log coefficients the network's output is the exponential of what the same weights give with a linear
    /// output, and the head's bias receives the analytic gradient: ∂Σ exp(z)/∂bias = Σ exp(z), since the bias
    /// adds to every pixel's z.
    #[test]
    fn log_coefficients_exponentiate_the_linear_output_and_carry_its_gradient() {
        let device = Default::default();
        let config = UNetConfig::new(1)
            .with_context_channels(2)
            .with_base_width(4)
            .with_dropout(false);
        let x = Tensor::<Ad, 4>::random([2, 1, 128, 128], Distribution::Normal(0.0, 1.0), &device);
        let context =
            Tensor::<Ad, 4>::random([2, 2, 32, 32], Distribution::Normal(0.0, 1.0), &device);
        let linear = config.init::<Ad>(&device);
        let a = linear.forward(x.clone(), Some(context.clone()));
        // The same weights (cloned after the forward pass: Burn initialises parameters lazily, on first use).
        let mut logarithmic = linear.clone();
        logarithmic.log_coefficients = true;
        let b = logarithmic.forward(x, Some(context));
        let worst = (a.clone().exp() - b.clone()).abs().max().into_scalar();
        assert_eq!(worst, 0.0, "exp of the linear output differs by {worst}");

        let total = b.sum();
        let expected: f32 = total.clone().into_scalar();
        let grads = total.backward();
        let bias = logarithmic.head.bias.as_ref().expect("the head has a bias");
        let got: f32 = bias.grad(&grads).expect("a gradient").into_scalar();
        let relative = ((got - expected) / expected).abs();
        assert!(
            relative < 1e-5,
            "bias gradient {got} against the output's sum {expected} (relative {relative:e}, tolerance 1e-5)"
        );
    }
}
