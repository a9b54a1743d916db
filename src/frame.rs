//! The frame: what a gradient-domain renderer hands to gdrecon.
//!
//! # Conventions (the contract is docs/CONVENTIONS.md; these are the ones every method relies on)
//! - Images are row-major, `y` grows downward and `x` to the right; pixel `(x, y)`.
//! - Gradients are forward differences: `dx(x, y) = I(x+1, y) - I(x, y)` and
//!   `dy(x, y) = I(x, y+1) - I(x, y)`. The last column of `dx` and the last row of `dy` carry
//!   no information: every method ignores them (Neumann boundary), writers store 0 there.
//! - All radiance buffers are linear HDR, f32, RGB. `variance` is the variance of the colour
//!   *mean* estimate (sample variance / spp).
//! - Features are stored as given; normalising them (normal to [0, 1], depth to [0, 1]) is the
//!   methods' job, not the caller's.
//!
//! A [`Frame`] can only be obtained through [`FrameBuilder`] (or the EXR reader, which uses
//! it), so every frame a method sees has been validated and sanitised: equal sizes, required
//! layers present, no NaN or Inf anywhere, no negative colour or variance.

use std::collections::BTreeMap;

use ndarray::ArrayView3;

use crate::error::{Error, Result};
use crate::image::Image;
use crate::validate::{gradient_bound, sanitize_layer, Policy, SanitizeReport, Summary};

/// A layer of a frame bundle, named as in the EXR bundle (`layer.component`).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
#[non_exhaustive]
pub enum Layer {
    /// Base (primal) image `I_b`, RGB. Required.
    Color,
    /// Horizontal forward-difference gradient, RGB. Required.
    Dx,
    /// Vertical forward-difference gradient, RGB. Required.
    Dy,
    /// Variance of the colour mean per pixel, RGB. Optional.
    Variance,
    /// First non-specular albedo, RGB, roughly in [0, 1]. Optional.
    Albedo,
    /// Shading normal, XYZ in [-1, 1]. Optional.
    Normal,
    /// Distance from the camera, one channel, any positive scale. Optional.
    Depth,
    /// Converged image, RGB; evaluation data only, never used by a method. Optional.
    Reference,
    /// A denoiser's output for this frame (e.g. Intel Open Image Denoise on `color`), RGB.
    /// Optional: the methods that use a prior compute one when it is absent.
    Prior,
}

impl Layer {
    /// Every layer, in bundle order.
    pub const ALL: [Layer; 9] = [
        Layer::Color,
        Layer::Dx,
        Layer::Dy,
        Layer::Variance,
        Layer::Albedo,
        Layer::Normal,
        Layer::Depth,
        Layer::Reference,
        Layer::Prior,
    ];

    /// The layer's name in a bundle (`color`, `dx`, ...).
    pub fn name(self) -> &'static str {
        match self {
            Layer::Color => "color",
            Layer::Dx => "dx",
            Layer::Dy => "dy",
            Layer::Variance => "variance",
            Layer::Albedo => "albedo",
            Layer::Normal => "normal",
            Layer::Depth => "depth",
            Layer::Reference => "reference",
            Layer::Prior => "prior",
        }
    }

    /// The layer's component names, in channel order.
    pub fn components(self) -> &'static [&'static str] {
        match self {
            Layer::Normal => &["X", "Y", "Z"],
            Layer::Depth => &["Z"],
            _ => &["R", "G", "B"],
        }
    }

    /// Number of channels the layer has.
    pub fn channels(self) -> usize {
        self.components().len()
    }

    /// Whether a frame is invalid without this layer.
    pub fn is_required(self) -> bool {
        matches!(self, Layer::Color | Layer::Dx | Layer::Dy)
    }

    /// Whether values are signed by nature (negative values are legitimate).
    pub fn is_signed(self) -> bool {
        matches!(self, Layer::Dx | Layer::Dy | Layer::Normal)
    }

    /// Whether a negative value is invalid and gets replaced (colour and variance; the
    /// reference and the prior are held to the same rule since they are colours).
    pub fn must_be_nonnegative(self) -> bool {
        matches!(
            self,
            Layer::Color | Layer::Variance | Layer::Reference | Layer::Prior
        )
    }

    /// Looks a layer up by its bundle name, case-insensitively.
    pub fn from_name(name: &str) -> Option<Layer> {
        Layer::ALL
            .into_iter()
            .find(|l| l.name().eq_ignore_ascii_case(name))
    }

    fn index(self) -> usize {
        self as usize
    }
}

impl std::fmt::Display for Layer {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

/// A validated gradient-domain frame: required colour and gradients, optional features,
/// variance, reference and sample count. See the module documentation for conventions.
#[derive(Clone, Debug)]
pub struct Frame {
    layers: [Option<Image>; Layer::ALL.len()],
    width: usize,
    height: usize,
    spp: Option<f32>,
    sanitized: SanitizeReport,
}

impl Frame {
    /// Width in pixels.
    pub fn width(&self) -> usize {
        self.width
    }

    /// Height in pixels.
    pub fn height(&self) -> usize {
        self.height
    }

    /// `(width, height)`.
    pub fn size(&self) -> (usize, usize) {
        (self.width, self.height)
    }

    /// A layer, if the frame has it.
    pub fn layer(&self, layer: Layer) -> Option<&Image> {
        self.layers[layer.index()].as_ref()
    }

    /// The base image `I_b`.
    pub fn color(&self) -> &Image {
        self.layers[Layer::Color.index()]
            .as_ref()
            .expect("validated frames always have color")
    }

    /// The horizontal gradient.
    pub fn dx(&self) -> &Image {
        self.layers[Layer::Dx.index()]
            .as_ref()
            .expect("validated frames always have dx")
    }

    /// The vertical gradient.
    pub fn dy(&self) -> &Image {
        self.layers[Layer::Dy.index()]
            .as_ref()
            .expect("validated frames always have dy")
    }

    /// Variance of the colour mean, if present.
    pub fn variance(&self) -> Option<&Image> {
        self.layer(Layer::Variance)
    }

    /// Albedo, if present.
    pub fn albedo(&self) -> Option<&Image> {
        self.layer(Layer::Albedo)
    }

    /// Shading normal, if present.
    pub fn normal(&self) -> Option<&Image> {
        self.layer(Layer::Normal)
    }

    /// Depth, if present.
    pub fn depth(&self) -> Option<&Image> {
        self.layer(Layer::Depth)
    }

    /// Converged reference, if present (evaluation data).
    pub fn reference(&self) -> Option<&Image> {
        self.layer(Layer::Reference)
    }

    /// A denoiser's output for this frame, if the caller gave one.
    pub fn prior(&self) -> Option<&Image> {
        self.layer(Layer::Prior)
    }

    /// Samples per pixel of the base image, when known.
    pub fn spp(&self) -> Option<f32> {
        self.spp
    }

    /// The layers the frame holds, in bundle order.
    pub fn present_layers(&self) -> Vec<Layer> {
        Layer::ALL
            .into_iter()
            .filter(|l| self.layers[l.index()].is_some())
            .collect()
    }

    /// What validation replaced, per layer.
    pub fn sanitized(&self) -> &SanitizeReport {
        &self.sanitized
    }

    /// The same frame with its samples per pixel set to `spp` (`None`: unknown), checked as
    /// [`FrameBuilder::build`] checks it. The layers and the report of replaced values stay
    /// as they are (rebuilding the frame would sanitise clean layers again and report nothing
    /// replaced).
    pub fn with_spp(mut self, spp: Option<f32>) -> Result<Frame> {
        check_spp(spp)?;
        self.spp = spp;
        Ok(self)
    }

    /// Takes the frame apart into a builder holding the same (already clean) layers, e.g. to
    /// drop or replace one.
    pub fn into_builder(self) -> FrameBuilder {
        FrameBuilder {
            layers: self.layers,
            spp: self.spp,
        }
    }
}

/// Refuses samples per pixel that are not a positive finite number.
fn check_spp(spp: Option<f32>) -> Result<()> {
    match spp {
        Some(s) if !(s.is_finite() && s > 0.0) => Err(Error::input(format!(
            "spp is {s}: samples per pixel must be a positive finite number (or unknown)"
        ))),
        _ => Ok(()),
    }
}

/// Collects the layers of a frame, then validates and sanitises them in [`FrameBuilder::build`].
///
/// Layers come either as owned planar [`Image`]s or as borrowed views of shape
/// `(height, width, channels)` with arbitrary strides, so interleaved RGB, RGBA (through a
/// 3-channel slice of the view) and planar caller buffers all work; views are copied once.
#[derive(Clone, Debug, Default)]
pub struct FrameBuilder {
    layers: [Option<Image>; Layer::ALL.len()],
    spp: Option<f32>,
}

impl FrameBuilder {
    /// An empty builder.
    pub fn new() -> Self {
        Self::default()
    }

    /// Sets a layer from an owned planar image (shape `(channels, height, width)`).
    pub fn image(mut self, layer: Layer, image: Image) -> Self {
        self.layers[layer.index()] = Some(image);
        self
    }

    /// Sets a layer from a strided view of shape `(height, width, channels)`.
    pub fn view(self, layer: Layer, view: ArrayView3<'_, f32>) -> Self {
        self.image(layer, Image::from_hwc(view))
    }

    /// Removes a layer.
    pub fn without(mut self, layer: Layer) -> Self {
        self.layers[layer.index()] = None;
        self
    }

    /// Sets the samples per pixel of the base image (`None`: unknown).
    pub fn spp(mut self, spp: Option<f32>) -> Self {
        self.spp = spp;
        self
    }

    /// Validates sizes and layers and sanitises values under `policy`.
    ///
    /// Errors: a missing required layer, a zero-sized image, a layer whose size or channel
    /// count disagrees, a non-positive or non-finite `spp`, and (strict policy only) any
    /// non-finite value or negative colour / variance. Otherwise bad values are replaced
    /// (non-finite by 0, negative colour and variance by 0) and counted in
    /// [`Frame::sanitized`].
    pub fn build(self, policy: Policy) -> Result<Frame> {
        self.build_known(policy, &BTreeMap::new())
    }

    /// [`FrameBuilder::build`], skipping the sanitising pass over a layer that `known`
    /// summarises as clean. The summaries must be of the layers' values as they are now (the
    /// reader makes them while decoding, then builds at once).
    pub(crate) fn build_known(
        self,
        policy: Policy,
        known: &BTreeMap<Layer, Summary>,
    ) -> Result<Frame> {
        let FrameBuilder { mut layers, spp } = self;
        let color = layers[Layer::Color.index()]
            .as_ref()
            .ok_or_else(|| missing(Layer::Color))?;
        let (width, height) = color.size();
        if width == 0 || height == 0 {
            return Err(Error::input(format!(
                "layer 'color' is {width} x {height}: an image needs at least one pixel"
            )));
        }
        for layer in Layer::ALL {
            match &layers[layer.index()] {
                None if layer.is_required() => return Err(missing(layer)),
                None => {}
                Some(img) => {
                    if img.size() != (width, height) {
                        return Err(Error::input(format!(
                            "layer '{layer}' is {} x {}, expected {width} x {height} like 'color'",
                            img.width(),
                            img.height()
                        )));
                    }
                    if img.channels() != layer.channels() {
                        return Err(Error::input(format!(
                            "layer '{layer}' has {} channels, expected {} ({})",
                            img.channels(),
                            layer.channels(),
                            layer.components().join(", ")
                        )));
                    }
                }
            }
        }
        check_spp(spp)?;
        let mut sanitized = SanitizeReport::default();
        let mut gradients = None;
        // Colour comes first in Layer::ALL: the gradients' bound is taken on the sanitised colour.
        for layer in Layer::ALL {
            let bound = matches!(layer, Layer::Dx | Layer::Dy).then(|| {
                *gradients.get_or_insert_with(|| match known.get(&Layer::Color) {
                    Some(color) if color.clean(Layer::Color, None) => color.gradient_bound(),
                    _ => gradient_bound(layers[Layer::Color.index()].as_ref().expect("checked")),
                })
            });
            if let Some(img) = layers[layer.index()].as_mut() {
                if known.get(&layer).is_some_and(|s| s.clean(layer, bound)) {
                    continue; // nothing to replace (and nothing for strict mode to refuse)
                }
                let counts = sanitize_layer(layer, img, policy, bound)?;
                sanitized.record(layer, counts);
            }
        }
        Ok(Frame {
            layers,
            width,
            height,
            spp,
            sanitized,
        })
    }
}

fn missing(layer: Layer) -> Error {
    Error::input(format!(
        "required layer '{layer}' ({}) is missing",
        layer
            .components()
            .iter()
            .map(|c| format!("{layer}.{c}"))
            .collect::<Vec<_>>()
            .join(", ")
    ))
}
