//! BTF compression (PCA, per-view factorization, …): being built, see issue "The
//! compression pipeline".
