//! A small dense autoencoder: tanh hidden layers and a linear output layer (so a reconstruction
//! can take any sign and size a standardised input can), trained with mini-batch Adam on the
//! mean squared reconstruction error. Plain Rust: the networks are tiny (MAVFI's is
//! 13 → 6 → 3 → 13, 211 parameters) and inference must not allocate.

use rand::seq::SliceRandom;
use rand::Rng;
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};

#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Activation {
    Tanh,
    Linear,
}

impl Activation {
    #[inline]
    fn apply(self, z: f64) -> f64 {
        match self {
            Activation::Tanh => z.tanh(),
            Activation::Linear => z,
        }
    }

    /// The derivative, from the activation's output `a`.
    #[inline]
    fn slope(self, a: f64) -> f64 {
        match self {
            Activation::Tanh => 1.0 - a * a,
            Activation::Linear => 1.0,
        }
    }
}

/// One dense layer: `out = activation(weights · in + bias)`, weights row-major
/// (`outputs` rows of `inputs`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Layer {
    pub inputs: usize,
    pub outputs: usize,
    pub activation: Activation,
    pub weights: Vec<f64>,
    pub bias: Vec<f64>,
}

impl Layer {
    #[inline]
    fn forward(&self, input: &[f64], out: &mut [f64]) {
        for ((o, row), b) in out
            .iter_mut()
            .zip(self.weights.chunks_exact(self.inputs))
            .zip(&self.bias)
        {
            let mut z = *b;
            for (w, x) in row.iter().zip(input) {
                z += w * x;
            }
            *o = self.activation.apply(z);
        }
    }
}

/// The default layer sizes for `n` inputs: n → ⌊n/2⌋ → ⌊n/4⌋ → n (each at least 1), which is
/// MAVFI's 13 → 6 → 3 → 13 for 13 fields.
pub fn default_sizes(n: usize) -> Vec<usize> {
    vec![n, (n / 2).max(1), (n / 4).max(1), n]
}

/// A dense feed-forward network.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(transparent)]
pub struct Network {
    pub layers: Vec<Layer>,
}

/// Per-layer output buffers, made once per network, reused for every frame.
#[derive(Debug, Clone)]
pub struct Scratch {
    outs: Vec<Box<[f64]>>,
}

impl Network {
    /// A freshly initialised network with layer widths `sizes` (input first): tanh on every
    /// layer but the last, which is linear. Weights are Xavier-uniform from `rng`, biases 0.
    pub fn new(sizes: &[usize], rng: &mut ChaCha8Rng) -> Self {
        let last = sizes.len().saturating_sub(2);
        let layers = sizes
            .windows(2)
            .enumerate()
            .map(|(k, w)| {
                let (inputs, outputs) = (w[0], w[1]);
                let limit = (6.0 / (inputs + outputs) as f64).sqrt();
                Layer {
                    inputs,
                    outputs,
                    activation: if k == last {
                        Activation::Linear
                    } else {
                        Activation::Tanh
                    },
                    weights: (0..inputs * outputs)
                        .map(|_| rng.gen_range(-limit..limit))
                        .collect(),
                    bias: vec![0.0; outputs],
                }
            })
            .collect();
        Network { layers }
    }

    pub fn inputs(&self) -> usize {
        self.layers.first().map_or(0, |l| l.inputs)
    }

    pub fn outputs(&self) -> usize {
        self.layers.last().map_or(0, |l| l.outputs)
    }

    pub fn parameters(&self) -> usize {
        self.layers
            .iter()
            .map(|l| l.weights.len() + l.bias.len())
            .sum()
    }

    /// Checks the shapes (a loaded file is untrusted): consecutive layers fit, weight and bias
    /// counts match, every number is finite.
    pub fn check(&self) -> Result<(), String> {
        if self.layers.is_empty() {
            return Err("the network has no layers".into());
        }
        for (k, l) in self.layers.iter().enumerate() {
            if l.inputs == 0 || l.outputs == 0 {
                return Err(format!("layer {k} has a zero width"));
            }
            if k > 0 && self.layers[k - 1].outputs != l.inputs {
                return Err(format!(
                    "layer {k} takes {} inputs but layer {} gives {}",
                    l.inputs,
                    k - 1,
                    self.layers[k - 1].outputs
                ));
            }
            if l.weights.len() != l.inputs * l.outputs {
                return Err(format!(
                    "layer {k} has {} weights, {}×{} expected",
                    l.weights.len(),
                    l.outputs,
                    l.inputs
                ));
            }
            if l.bias.len() != l.outputs {
                return Err(format!(
                    "layer {k} has {} biases, {} expected",
                    l.bias.len(),
                    l.outputs
                ));
            }
            if !l.weights.iter().chain(&l.bias).all(|v| v.is_finite()) {
                return Err(format!("layer {k} has a non-finite parameter"));
            }
        }
        Ok(())
    }

    pub fn scratch(&self) -> Scratch {
        Scratch {
            outs: self
                .layers
                .iter()
                .map(|l| vec![0.0; l.outputs].into_boxed_slice())
                .collect(),
        }
    }

    /// Runs the network on `input` without allocating; the output is the scratch's last buffer.
    /// `scratch` must come from [`scratch`](Self::scratch) of this network.
    #[inline]
    pub fn forward<'s>(&self, input: &[f64], scratch: &'s mut Scratch) -> &'s [f64] {
        let outs = &mut scratch.outs;
        for (k, layer) in self.layers.iter().enumerate() {
            let (done, rest) = outs.split_at_mut(k);
            let src: &[f64] = if k == 0 { input } else { &done[k - 1] };
            layer.forward(src, &mut rest[0]);
        }
        outs.last().map_or(&[], |o| o)
    }

    /// Mean squared difference between `input` and its reconstruction.
    pub fn reconstruction_error(&self, input: &[f64], scratch: &mut Scratch) -> f64 {
        let out = self.forward(input, scratch);
        mean_squared(input, out)
    }
}

#[inline]
pub fn mean_squared(a: &[f64], b: &[f64]) -> f64 {
    let sum: f64 = a.iter().zip(b).map(|(x, y)| (x - y) * (x - y)).sum();
    sum / a.len().max(1) as f64
}

/// How to train.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Sgd {
    pub epochs: usize,
    pub batch: usize,
    pub learning_rate: f64,
}

impl Default for Sgd {
    fn default() -> Self {
        Sgd {
            epochs: 100,
            batch: 32,
            learning_rate: 3e-3,
        }
    }
}

/// Trains `net` to reproduce its inputs (`rows`, `net.inputs()` values each) with Adam on the
/// mean squared error; returns the mean loss of every epoch. Deterministic for a given `rng`.
pub fn train(net: &mut Network, rows: &[f64], sgd: Sgd, rng: &mut ChaCha8Rng) -> Vec<f64> {
    let n = net.inputs();
    let count = rows.len() / n.max(1);
    if count == 0 {
        return Vec::new();
    }
    const BETA1: f64 = 0.9;
    const BETA2: f64 = 0.999;
    const EPS: f64 = 1e-8;
    let sizes: Vec<usize> = net.layers.iter().map(|l| l.weights.len()).collect();
    let zeros_w = || -> Vec<Vec<f64>> { sizes.iter().map(|&s| vec![0.0; s]).collect() };
    let zeros_b = |net: &Network| -> Vec<Vec<f64>> {
        net.layers.iter().map(|l| vec![0.0; l.outputs]).collect()
    };
    let (mut gw, mut gb) = (zeros_w(), zeros_b(net));
    let (mut mw, mut mb, mut vw, mut vb) = (zeros_w(), zeros_b(net), zeros_w(), zeros_b(net));
    let mut acts: Vec<Vec<f64>> = net.layers.iter().map(|l| vec![0.0; l.outputs]).collect();
    let mut deltas = acts.clone();
    let mut order: Vec<usize> = (0..count).collect();
    let mut step = 0i32;
    let mut losses = Vec::with_capacity(sgd.epochs);
    let batch = sgd.batch.max(1);
    for _ in 0..sgd.epochs {
        order.shuffle(rng);
        let mut epoch_loss = 0.0;
        for chunk in order.chunks(batch) {
            gw.iter_mut().chain(gb.iter_mut()).for_each(|g| g.fill(0.0));
            for &r in chunk {
                let x = &rows[r * n..(r + 1) * n];
                // Forward, keeping every layer's output.
                for k in 0..net.layers.len() {
                    let (done, rest) = acts.split_at_mut(k);
                    let src: &[f64] = if k == 0 { x } else { &done[k - 1] };
                    net.layers[k].forward(src, &mut rest[0]);
                }
                let out = &acts[acts.len() - 1];
                epoch_loss += mean_squared(x, out);
                // Backward: d(loss)/d(output) of the mean squared error, then through layers.
                let last = net.layers.len() - 1;
                for ((d, y), t) in deltas[last].iter_mut().zip(out).zip(x) {
                    *d = 2.0 * (y - t) / n as f64;
                }
                for k in (0..net.layers.len()).rev() {
                    let layer = &net.layers[k];
                    for (d, a) in deltas[k].iter_mut().zip(&acts[k]) {
                        *d *= layer.activation.slope(*a);
                    }
                    let src: &[f64] = if k == 0 { x } else { &acts[k - 1] };
                    for (j, d) in deltas[k].iter().enumerate() {
                        gb[k][j] += d;
                        let row = &mut gw[k][j * layer.inputs..(j + 1) * layer.inputs];
                        for (g, s) in row.iter_mut().zip(src) {
                            *g += d * s;
                        }
                    }
                    if k > 0 {
                        let (before, after) = deltas.split_at_mut(k);
                        let down = &mut before[k - 1];
                        down.fill(0.0);
                        for (j, d) in after[0].iter().enumerate() {
                            let row = &layer.weights[j * layer.inputs..(j + 1) * layer.inputs];
                            for (b, w) in down.iter_mut().zip(row) {
                                *b += w * d;
                            }
                        }
                    }
                }
            }
            // Adam step on the batch's mean gradient.
            step += 1;
            let scale = 1.0 / chunk.len() as f64;
            let c1 = 1.0 - BETA1.powi(step);
            let c2 = 1.0 - BETA2.powi(step);
            let lr = sgd.learning_rate;
            let update = |p: &mut [f64], g: &[f64], m: &mut [f64], v: &mut [f64]| {
                for i in 0..p.len() {
                    let gi = g[i] * scale;
                    m[i] = BETA1 * m[i] + (1.0 - BETA1) * gi;
                    v[i] = BETA2 * v[i] + (1.0 - BETA2) * gi * gi;
                    p[i] -= lr * (m[i] / c1) / ((v[i] / c2).sqrt() + EPS);
                }
            };
            for (k, layer) in net.layers.iter_mut().enumerate() {
                update(&mut layer.weights, &gw[k], &mut mw[k], &mut vw[k]);
                update(&mut layer.bias, &gb[k], &mut mb[k], &mut vb[k]);
            }
        }
        losses.push(epoch_loss / count as f64);
    }
    losses
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;

    #[test]
    fn default_shape_is_mavfis() {
        assert_eq!(default_sizes(13), vec![13, 6, 3, 13]);
        assert_eq!(default_sizes(1), vec![1, 1, 1, 1]);
        let net = Network::new(&default_sizes(13), &mut ChaCha8Rng::seed_from_u64(1));
        assert_eq!(net.parameters(), 13 * 6 + 6 + 6 * 3 + 3 + 3 * 13 + 13);
        assert_eq!(net.layers[2].activation, Activation::Linear);
        assert!(net.check().is_ok());
    }

    /// The output layer is linear: a network can reproduce negative and large targets, which a
    /// ReLU or sigmoid output (MAVFI's released code) cannot.
    #[test]
    fn linear_output_reaches_negative_values() {
        let seed = 7;
        println!("seed {seed}");
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let mut net = Network::new(&[2, 2, 2], &mut rng);
        // Data on a line through negative territory well beyond tanh's range.
        let rows: Vec<f64> = (0..200)
            .flat_map(|i| {
                let t = -3.0 + 6.0 * i as f64 / 199.0;
                [t, -2.0 * t]
            })
            .collect();
        let losses = train(
            &mut net,
            &rows,
            Sgd {
                epochs: 300,
                batch: 16,
                learning_rate: 1e-2,
            },
            &mut rng,
        );
        let mut scratch = net.scratch();
        let out = net.forward(&[3.0, -6.0], &mut scratch).to_vec();
        assert!(out[1] < -4.0, "reconstruction {out:?}");
        assert!(losses.last().unwrap() < &losses[0]);
    }

    #[test]
    fn check_rejects_bad_shapes() {
        let mut net = Network::new(&[4, 2, 4], &mut ChaCha8Rng::seed_from_u64(3));
        net.layers[1].inputs = 3;
        assert!(net.check().unwrap_err().contains("layer 1 takes 3 inputs"));
        let mut net = Network::new(&[4, 2, 4], &mut ChaCha8Rng::seed_from_u64(3));
        net.layers[0].bias.pop();
        assert!(net.check().unwrap_err().contains("biases"));
        let mut net = Network::new(&[4, 2, 4], &mut ChaCha8Rng::seed_from_u64(3));
        net.layers[0].weights[0] = f64::NAN;
        assert!(net.check().unwrap_err().contains("non-finite"));
    }
}
