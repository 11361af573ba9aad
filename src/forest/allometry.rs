//! Per-tree basal area, stem volume, above-ground biomass and carbon from the measured DBH and
//! height (issue 27.2), each from a named equation whose constants are parameters of the job.
//!
//! - Basal area: BA = π (DBH / 2)², the stem's cross-section at breast height.
//! - Stem volume: V = f · BA · H, with the breast-height form factor f, the ratio of the stem's
//!   volume to that of a cylinder of the same basal area and height (forest mensuration's
//!   standard generic model; f ≈ 0.45–0.55 for most temperate species, so 0.5 by default).
//! - Above-ground biomass: Chave et al. 2014 ("Improved allometric models to estimate the
//!   aboveground biomass of tropical trees", Global Change Biology 20:3177–3190), equation 4:
//!   AGB = 0.0673 · (ρ D² H)^0.976, AGB in kg, ρ wood density in g/cm³, D in cm, H in m. It is
//!   the generic model the issue names; with no species-specific model it is a documented,
//!   citable default, not a local truth.
//! - Carbon: C = CF · AGB, CF = 0.47 (IPCC 2006 Guidelines, Vol. 4, Ch. 4, Table 4.3).
//!
//! Volume and biomass need the height: a tree without one gets neither.

use serde::{Deserialize, Serialize};

use super::ForestError;

/// The constants of the allometric equations; every output names the equations it used.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(default, deny_unknown_fields)]
pub struct AllometryParams {
    /// Wood density ρ of Chave et al. 2014 eq. 4, g/cm³ (oven-dry mass over green volume).
    /// Default 0.5: the middle of IPCC 2006 Vol. 4 Table 4.14's temperate species (about
    /// 0.40 for spruce and pine to 0.58 for beech and oak); give your species' value.
    pub wood_density_g_cm3: f64,
    /// Breast-height form factor f of V = f · BA · H (default 0.5, see the module doc).
    pub form_factor: f64,
    /// Carbon fraction of dry biomass (default 0.47, IPCC 2006 Vol. 4 Ch. 4 Table 4.3).
    pub carbon_fraction: f64,
}

impl Default for AllometryParams {
    fn default() -> Self {
        Self {
            wood_density_g_cm3: 0.5,
            form_factor: 0.5,
            carbon_fraction: 0.47,
        }
    }
}

impl AllometryParams {
    /// Refuses constants outside what wood and stems can be.
    pub fn validate(&self) -> Result<(), ForestError> {
        let within = |v: f64, lo: f64, hi: f64| v.is_finite() && v > lo && v <= hi;
        if !within(self.wood_density_g_cm3, 0.05, 1.5) {
            return Err(ForestError::Params(format!(
                "allometry: wood_density_g_cm3 must be in (0.05, 1.5] g/cm³, got {}",
                self.wood_density_g_cm3
            )));
        }
        if !within(self.form_factor, 0.0, 1.0) {
            return Err(ForestError::Params(format!(
                "allometry: form_factor must be in (0, 1], got {}",
                self.form_factor
            )));
        }
        if !within(self.carbon_fraction, 0.0, 1.0) {
            return Err(ForestError::Params(format!(
                "allometry: carbon_fraction must be in (0, 1], got {}",
                self.carbon_fraction
            )));
        }
        Ok(())
    }

    /// The equations with these constants, as the outputs name them.
    pub fn equations(&self) -> Equations {
        Equations {
            basal_area: "BA = pi (DBH / 2)^2".into(),
            volume: format!(
                "V = f BA H, breast-height form factor f = {}",
                self.form_factor
            ),
            biomass: format!(
                "Chave et al. 2014 eq. 4: AGB [kg] = 0.0673 (rho D^2 H)^0.976, D in cm, H in m, \
                 wood density rho = {} g/cm3",
                self.wood_density_g_cm3
            ),
            carbon: format!(
                "C = {} AGB (IPCC 2006 Vol. 4 Ch. 4 Table 4.3 carbon fraction)",
                self.carbon_fraction
            ),
        }
    }
}

/// The equations behind each figure, in words and symbols.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Equations {
    pub basal_area: String,
    pub volume: String,
    pub biomass: String,
    pub carbon: String,
}

/// One tree's figures.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct TreeAllometry {
    /// Basal area, m².
    pub basal_area_m2: f64,
    /// Stem volume, m³ (`None` without a height).
    pub volume_m3: Option<f64>,
    /// Above-ground biomass, kg dry mass (`None` without a height).
    pub agb_kg: Option<f64>,
    /// Carbon, kg (`None` without a height).
    pub carbon_kg: Option<f64>,
}

/// The figures of a tree of `dbh_cm` (centimetres) and `height_m` (metres).
pub fn tree_allometry(dbh_cm: f64, height_m: Option<f64>, p: &AllometryParams) -> TreeAllometry {
    let basal_area_m2 = std::f64::consts::PI * (dbh_cm / 200.0).powi(2);
    let height_m = height_m.filter(|h| h.is_finite() && *h > 0.0);
    let volume_m3 = height_m.map(|h| p.form_factor * basal_area_m2 * h);
    let agb_kg =
        height_m.map(|h| 0.0673 * (p.wood_density_g_cm3 * dbh_cm * dbh_cm * h).powf(0.976));
    TreeAllometry {
        basal_area_m2,
        volume_m3,
        agb_kg,
        carbon_kg: agb_kg.map(|a| a * p.carbon_fraction),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Hand-computed values: a 30 cm, 20 m tree with the defaults.
    /// BA = π 0.15² = 0.0706858 m²; V = 0.5 · 0.0706858 · 20 = 0.706858 m³;
    /// ρ D² H = 0.5 · 900 · 20 = 9000, 9000^0.976 = 7233.37, AGB = 0.0673 · 7233.37 = 486.81 kg;
    /// C = 0.47 · 486.81 = 228.80 kg.
    #[test]
    fn a_thirty_centimetre_tree_of_twenty_metres() {
        let a = tree_allometry(30.0, Some(20.0), &AllometryParams::default());
        assert!((a.basal_area_m2 - 0.070_685_8).abs() < 1e-6, "{a:?}");
        assert!(
            (a.volume_m3.unwrap_or(0.0) - 0.706_858).abs() < 1e-5,
            "{a:?}"
        );
        let agb = a.agb_kg.unwrap_or(0.0);
        assert!((agb - 486.806).abs() < 0.01, "{a:?}");
        assert!(
            (a.carbon_kg.unwrap_or(0.0) - 0.47 * agb).abs() < 1e-9,
            "{a:?}"
        );
        let no_height = tree_allometry(30.0, None, &AllometryParams::default());
        assert_eq!((no_height.volume_m3, no_height.agb_kg), (None, None));
        assert!(
            AllometryParams::default()
                .equations()
                .biomass
                .contains("Chave")
        );
        let bad = AllometryParams {
            wood_density_g_cm3: 5.0,
            ..AllometryParams::default()
        };
        assert!(bad.validate().is_err());
    }
}
