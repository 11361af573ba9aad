//! The GPU context. For now: find an adapter through wgpu (Vulkan; lavapipe on machines
//! without a GPU) so `/v1/info` can say what the trainer will run on.

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
