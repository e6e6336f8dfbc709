"""Canonical systems: reference fields for training, tests and documentation.

Every generator returns its field as an :class:`xarray.DataArray` in the field
layout of latticedft (time first, ``x`` last, uniform float64 coordinates,
``long_name``/``units``/``source`` attributes; see
:mod:`latticedft.systems._fields`). The package is split by family; import
every name from here (``from latticedft import systems; systems.leapfrog``):

* Paper (Qin 2020) Example 1, :func:`oscillator_sin`; Example 2,
  :func:`oscillator_wells` (:mod:`~latticedft.systems.oscillators`);
  Section 4, the Kepler problem (:data:`PLANETS`, :func:`kepler_orbit`,
  :func:`planet_orbit`; :mod:`~latticedft.systems.kepler`).
* The wave equation, exact: :func:`wave_string` (1+1D) and
  :func:`wave_membrane` (2+1D) (:mod:`~latticedft.systems.waves`).
* The explicit leapfrog scheme of ``psi_tt = c^2 Laplacian(psi) + f(psi)``,
  :func:`leapfrog` (baseline and numpy speed reference;
  :mod:`~latticedft.systems.leapfrog_scheme`).
* The periodic Klein–Gordon benchmark: :func:`klein_gordon`,
  :func:`klein_gordon_training_set`, :func:`klein_gordon_test_field`
  (:mod:`~latticedft.systems.klein_gordon_data`).
* Sine-Gordon, exact: :func:`sine_gordon_breather`, :func:`kink_antikink`,
  and :func:`sine_gordon_energy` (:mod:`~latticedft.systems.sine_gordon`).
* A charged particle in a uniform magnetic field (a Lagrangian linear in the
  velocity), exact: :func:`charged_particle` and :func:`cyclotron_energy`
  (:mod:`~latticedft.systems.magnetic`).
* Energies of served fields: :func:`field_energy`, :func:`wave_energy`
  (string and membrane) and :func:`klein_gordon_energy`
  (:mod:`~latticedft.systems.energy`).
* :func:`make_field` builds a DataArray in this layout from plain arrays.

Reference ODE solutions use :func:`scipy.integrate.solve_ivp` with the
8th-order Dormand–Prince method (DOP853), ``rtol = atol = 1e-12``, sampled at
the lattice times through ``t_eval`` (the method's dense output).
"""

from __future__ import annotations

from latticedft.systems._fields import ODE_ATOL, ODE_RTOL, make_field
from latticedft.systems.energy import field_energy, klein_gordon_energy, wave_energy
from latticedft.systems.kepler import (
    GM_SUN_KEPLER_UNITS,
    KEPLER_TIME_UNIT_DAYS,
    PLANETS,
    Planet,
    escape_speed,
    kepler_angular_momentum,
    kepler_energy,
    kepler_orbit,
    kepler_period,
    planet_aphelion,
    planet_orbit,
)
from latticedft.systems.klein_gordon_data import (
    klein_gordon,
    klein_gordon_test_field,
    klein_gordon_training_set,
)
from latticedft.systems.leapfrog_scheme import leapfrog
from latticedft.systems.magnetic import charged_particle, cyclotron_energy
from latticedft.systems.oscillators import (
    oscillator_sin,
    oscillator_sin_energy,
    oscillator_wells,
    oscillator_wells_energy,
    wells_potential,
)
from latticedft.systems.sine_gordon import (
    kink_antikink,
    sine_gordon_breather,
    sine_gordon_energy,
)
from latticedft.systems.waves import wave_membrane, wave_string

__all__ = [
    "ODE_RTOL",
    "ODE_ATOL",
    "KEPLER_TIME_UNIT_DAYS",
    "GM_SUN_KEPLER_UNITS",
    "Planet",
    "PLANETS",
    "make_field",
    "oscillator_sin",
    "oscillator_sin_energy",
    "oscillator_wells",
    "wells_potential",
    "oscillator_wells_energy",
    "kepler_orbit",
    "planet_orbit",
    "planet_aphelion",
    "kepler_energy",
    "kepler_angular_momentum",
    "kepler_period",
    "escape_speed",
    "wave_string",
    "wave_membrane",
    "leapfrog",
    "klein_gordon",
    "klein_gordon_training_set",
    "klein_gordon_test_field",
    "sine_gordon_breather",
    "kink_antikink",
    "sine_gordon_energy",
    "charged_particle",
    "cyclotron_energy",
    "field_energy",
    "wave_energy",
    "klein_gordon_energy",
]
