//! The GPU layer under the trainer's kernels, on wgpu: the adapter probe `/v1/info` uses
//! ([`probe`]), the device context with what the adapter can do ([`context`]), buffer and
//! pipeline helpers ([`buffers`]), the prefix sum ([`scan`]) and radix sort ([`sort`]) any
//! kernel may use, and per-pass timing ([`timing`]). The splatting kernels themselves are in
//! `splat::gpu`.

pub mod buffers;
pub mod context;
pub mod scan;
pub mod sort;
pub mod timing;

use serde::Serialize;

/// The adapter the trainer would use.
#[derive(Debug, Clone, Serialize)]
pub struct GpuInfo {
    pub name: String,
    pub backend: String,
    pub device_type: String,
}

/// Looks for an adapter, honouring `WGPU_BACKEND` and friends. `None` when there is none;
/// never panics.
pub async fn probe() -> Option<GpuInfo> {
    let instance =
        wgpu::Instance::new(wgpu::InstanceDescriptor::new_without_display_handle_from_env());
    let adapter = instance
        .request_adapter(&wgpu::RequestAdapterOptions {
            power_preference: wgpu::PowerPreference::HighPerformance,
            force_fallback_adapter: false,
            compatible_surface: None,
            ..Default::default()
        })
        .await
        .ok()?;
    let info = adapter.get_info();
    Some(GpuInfo {
        name: info.name,
        backend: format!("{:?}", info.backend).to_lowercase(),
        device_type: format!("{:?}", info.device_type).to_lowercase(),
    })
}
