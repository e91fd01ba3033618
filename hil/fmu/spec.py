"""Model specifications: each FMU's variables, declared once in `fmus/NAME/model.toml`.

From a `ModelSpec` this module generates everything else that names a variable: the C header
`model_variables.h` (value references, the variable table with start values and ranges) and
`modelDescription.xml` (names, causality, variability, units, start values, descriptions, model
structure). Invariant: value references are positions in the declaration order (parameters, then
inputs, then outputs), so C and XML cannot disagree.
"""

from __future__ import annotations

import dataclasses
import datetime
import hashlib
import importlib.metadata
import math
import os
import subprocess
import tomllib
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path

from hil.errors import BuildError

GENERATOR = "softhil"
# A fixed date for sources outside a git checkout (the FMU zip's entries carry the same date).
_FALLBACK_DATE = datetime.datetime(2020, 1, 1, tzinfo=datetime.UTC)


def generator_version() -> str:
    """The installed softhil version, or "unknown" when run from an uninstalled tree."""
    try:
        return importlib.metadata.version("softhil")
    except importlib.metadata.PackageNotFoundError:
        return "unknown"


def generation_date(spec: ModelSpec) -> str:
    """generationDateAndTime derived from the sources, never from the clock, so that a build is
    byte-reproducible: $SOURCE_DATE_EPOCH if set (reproducible-builds.org), else the commit date
    of the newest commit touching the model's folder or the shared glue, else a fixed date."""
    epoch = os.environ.get("SOURCE_DATE_EPOCH")
    when = _FALLBACK_DATE
    if epoch and epoch.isdigit():
        when = datetime.datetime.fromtimestamp(int(epoch), tz=datetime.UTC)
    else:
        root = spec.folder.parent
        try:
            result = subprocess.run(
                [
                    "git",
                    "log",
                    "-1",
                    "--format=%ct",
                    "--",
                    str(spec.folder),
                    str(root / "common"),
                    str(root / "include"),
                ],
                cwd=spec.folder,
                capture_output=True,
                text=True,
                timeout=30,
                check=False,
            )
            stamp = result.stdout.strip()
            if result.returncode == 0 and stamp.isdigit():
                when = datetime.datetime.fromtimestamp(int(stamp), tz=datetime.UTC)
        except (OSError, subprocess.SubprocessError):
            pass
    return when.strftime("%Y-%m-%dT%H:%M:%SZ")


# SI units the models may use, as exponents of the base units (FMI 2.0 BaseUnit) and a factor.
_UNITS: dict[str, dict[str, float]] = {
    "1": {},
    "m": {"m": 1},
    "m/s": {"m": 1, "s": -1},
    "m/s2": {"m": 1, "s": -2},
    "m2": {"m": 2},
    "m3": {"m": 3},
    "m3/Pa": {"kg": -1, "m": 4, "s": 2},
    "m3/rad": {"m": 3, "rad": -1},
    "J": {"kg": 1, "m": 2, "s": -2},
    "kg": {"kg": 1},
    "kg/s": {"kg": 1, "s": -1},
    "kg/m3": {"kg": 1, "m": -3},
    "kg.m2": {"kg": 1, "m": 2},
    "s": {"s": 1},
    "Hz": {"s": -1},
    "rad": {"rad": 1},
    "rad/s": {"rad": 1, "s": -1},
    "1/m": {"m": -1},
    "N": {"kg": 1, "m": 1, "s": -2},
    "N.s/m": {"kg": 1, "s": -1},
    "N.s/m2": {"kg": 1, "m": -1, "s": -1},
    "N.s": {"kg": 1, "m": 1, "s": -1},
    "N/m": {"kg": 1, "s": -2},
    "rad/(N.m.s)": {"kg": -1, "m": -2, "s": 1, "rad": 1},
    "N.m": {"kg": 1, "m": 2, "s": -2},
    "N.m/rad": {"kg": 1, "m": 2, "s": -2, "rad": -1},
    "N.m.s/rad": {"kg": 1, "m": 2, "s": -1, "rad": -1},
    "N.m/A": {"kg": 1, "m": 2, "s": -2, "A": -1},
    "Pa": {"kg": 1, "m": -1, "s": -2},
    "K": {"K": 1},
    "J/(kg.K)": {"m": 2, "s": -2, "K": -1},
    "kg/(s.Pa)": {"m": 1, "s": 1},
    "A": {"A": 1},
    "V": {"kg": 1, "m": 2, "s": -3, "A": -1},
    "V/m": {"kg": 1, "m": 1, "s": -3, "A": -1},
    "V/(m.s)": {"kg": 1, "m": 1, "s": -4, "A": -1},
    "V.s/m": {"kg": 1, "m": 1, "s": -2, "A": -1},
    "V.s/rad": {"kg": 1, "m": 2, "s": -2, "A": -1, "rad": -1},
    "Ohm": {"kg": 1, "m": 2, "s": -3, "A": -2},
    "H": {"kg": 1, "m": 2, "s": -2, "A": -2},
}
# Human-facing display units (mm and kPa only in human-facing text).
_DISPLAY_UNITS: dict[str, list[tuple[str, float]]] = {
    "m": [("mm", 1e-3)],
    "Pa": [("kPa", 1e3)],
    "rad": [("deg", math.pi / 180.0)],
    "m3": [("mL", 1e-6)],
}

CAUSALITIES = ("parameters", "inputs", "outputs")
_TYPES = ("Real", "Integer", "Boolean")
_VARIABLE_KEYS = {"type", "unit", "start", "min", "max", "description", "depends_on", "count"}
MAX_FAMILY = 64  # members of one indexed family


@dataclass(frozen=True)
class Variable:
    """One model variable as declared in model.toml."""

    name: str
    causality: str  # "parameter" | "input" | "output"
    type: str  # "Real" | "Integer" | "Boolean"
    value_reference: int
    description: str
    unit: str | None = None
    start: float | None = None
    min: float | None = None
    max: float | None = None
    # inputs and parameters an output follows in initialisation mode (its initial dependencies)
    depends_on: tuple[str, ...] = ()

    @property
    def variability(self) -> str:
        if self.causality == "parameter":
            return "fixed"
        return "continuous" if self.type == "Real" else "discrete"


@dataclass(frozen=True)
class ModelSpec:
    """A model: its identifier, description, default step and variables."""

    name: str
    description: str
    step_size: float
    variables: tuple[Variable, ...]
    folder: Path
    # indexed families: base name -> number of members (NAME_1 ... NAME_N)
    families: tuple[tuple[str, int], ...] = ()

    def variable(self, name: str) -> Variable:
        for v in self.variables:
            if v.name == name:
                return v
        raise KeyError(name)

    def by_causality(self, causality: str) -> list[Variable]:
        return [v for v in self.variables if v.causality == causality]


# model.toml read and checked, by path, with the (mtime_ns, size) it had: a scenario's check asks
# for each model's spec a dozen times (its ports, defaults, parameters), a sweep's plan for every
# grid point, and parsing one costs 2-6 ms; a spec is immutable, so one object serves them all
_SPECS: dict[Path, tuple[tuple[int, int], ModelSpec]] = {}


def load_spec(folder: Path) -> ModelSpec:
    """Read and check `folder/model.toml`; every problem names the file and key. The spec is
    read again only when the file changes (its modification time or size)."""
    path = folder / "model.toml"
    try:
        stat = path.stat()
    except OSError as exc:
        raise BuildError(f"{path}: {exc}") from exc
    stamp = (stat.st_mtime_ns, stat.st_size)
    known = _SPECS.get(path)
    if known is not None and known[0] == stamp:
        return known[1]
    spec = _read_spec(folder, path)
    _SPECS[path] = (stamp, spec)
    return spec


def _read_spec(folder: Path, path: Path) -> ModelSpec:
    try:
        data = tomllib.loads(path.read_text())
    except (OSError, tomllib.TOMLDecodeError) as exc:
        raise BuildError(f"{path}: {exc}") from exc
    model = data.get("model")
    if not isinstance(model, dict) or "name" not in model:
        raise BuildError(f"{path}: [model] with a name is required")
    name = str(model["name"])
    if name != folder.name or not name.isidentifier():
        raise BuildError(f"{path}: model.name {name!r} must equal the folder name {folder.name!r}")
    variables, families = _declared(path, data)
    unknown = set(data) - {"model", *CAUSALITIES}
    if unknown:
        raise BuildError(f"{path}: unknown table(s) {sorted(unknown)}")
    return ModelSpec(
        name=name,
        description=str(model.get("description", "")),
        step_size=float(model.get("step_size", 1e-3)),
        variables=tuple(variables),
        folder=folder,
        families=tuple(families.items()),
    )


def _declared(path: Path, data: dict) -> tuple[list[Variable], dict[str, int]]:
    """The variables `data` declares, in value-reference order (parameters, inputs, outputs;
    a family as its members), their dependencies expanded and checked; and the families."""
    variables: list[Variable] = []
    families: dict[str, int] = {}
    for group in CAUSALITIES:
        for var_name, decl in data.get(group, {}).items():
            if isinstance(decl, dict) and "count" in decl:
                members = _family(path, group, var_name, decl)
                families[var_name] = len(members)
                for member_name, member in members:
                    variables.append(_variable(path, group, member_name, member, len(variables)))
            else:
                variables.append(_variable(path, group, var_name, decl, len(variables)))
    known = {v.name: v for v in variables}
    if len(known) != len(variables):
        names = [v.name for v in variables]
        twice = sorted({n for n in names if names.count(n) > 1})
        raise BuildError(f"{path}: variable(s) {twice} declared twice (a family member?)")
    if families:
        variables = [_expand_dependencies(v, families) for v in variables]
    _check_dependencies(path, variables, known)
    return variables, families


def _check_dependencies(path: Path, variables: list[Variable], known: dict[str, Variable]) -> None:
    """Every name in an output's depends_on is an input or a parameter of the model."""
    for v in variables:
        for dependency in v.depends_on:
            if dependency not in known or known[dependency].causality == "output":
                raise BuildError(
                    f"{path}: outputs.{v.name}.depends_on: {dependency!r} is not an input or "
                    "parameter"
                )


def _family(path: Path, group: str, name: str, decl: dict) -> list[tuple[str, dict]]:
    """The member declarations `NAME_1` ... `NAME_N` of an indexed family (`count = N`)."""
    key = f"{group}.{name}"
    count = decl["count"]
    if not isinstance(count, int) or isinstance(count, bool) or not 1 <= count <= MAX_FAMILY:
        raise BuildError(f"{path}: {key}.count must be an integer in [1, {MAX_FAMILY}]")
    start = decl.get("start")
    if isinstance(start, list) and len(start) != count:
        raise BuildError(f"{path}: {key}.start has {len(start)} values for count = {count}")
    members = []
    for i in range(1, count + 1):
        member = {k: v for k, v in decl.items() if k != "count"}
        if isinstance(start, list):
            member["start"] = start[i - 1]
        if "description" in member:
            member["description"] = str(member["description"]).replace("{i}", str(i))
        members.append((f"{name}_{i}", member))
    return members


def _expand_dependencies(v: Variable, families: dict[str, int]) -> Variable:
    """`depends_on` with every family name replaced by its members."""
    expanded: list[str] = []
    for name in v.depends_on:
        if name in families:
            expanded += [f"{name}_{i}" for i in range(1, families[name] + 1)]
        else:
            expanded.append(name)
    return dataclasses.replace(v, depends_on=tuple(expanded))


def _variable(path: Path, group: str, name: str, decl: object, vr: int) -> Variable:
    key = f"{group}.{name}"
    if not isinstance(decl, dict):
        raise BuildError(f"{path}: {key} must be a table")
    extra = set(decl) - _VARIABLE_KEYS
    if extra:
        raise BuildError(f"{path}: {key}: unknown key(s) {sorted(extra)}")
    if not name.isidentifier():
        raise BuildError(f"{path}: {key}: not a C identifier")
    vtype = decl.get("type", "Real")
    if vtype not in _TYPES:
        raise BuildError(f"{path}: {key}.type must be one of {_TYPES}")
    unit = decl.get("unit")
    if unit is not None and unit not in _UNITS:
        raise BuildError(f"{path}: {key}.unit {unit!r} is not a known unit")
    causality = group[:-1]
    start = decl.get("start")
    if causality != "output" and start is None:
        raise BuildError(f"{path}: {key}.start is required for a {causality}")
    if causality == "output" and start is not None:
        raise BuildError(f"{path}: {key}: outputs are calculated and take no start value")
    depends_on = decl.get("depends_on", [])
    if causality != "output" and depends_on:
        raise BuildError(f"{path}: {key}.depends_on is only for outputs")
    if not isinstance(depends_on, list) or not all(isinstance(n, str) for n in depends_on):
        raise BuildError(f"{path}: {key}.depends_on must be a list of variable names")
    return Variable(
        name=name,
        causality=causality,
        type=vtype,
        value_reference=vr,
        description=str(decl.get("description", "")),
        unit=unit,
        start=None if start is None else float(start),
        min=None if decl.get("min") is None else float(decl["min"]),
        max=None if decl.get("max") is None else float(decl["max"]),
        depends_on=tuple(depends_on),
    )


def guid(spec: ModelSpec, sources_digest: str) -> str:
    """GUID derived from the sources, so a changed model can never load a stale description."""
    h = hashlib.sha256(f"{spec.name}:{sources_digest}".encode()).hexdigest()
    return "{" + f"{h[:8]}-{h[8:12]}-{h[12:16]}-{h[16:20]}-{h[20:32]}" + "}"


def _c_double(value: float) -> str:
    return repr(float(value)) if math.isfinite(value) else "0.0"


def generate_header(spec: ModelSpec, model_guid: str) -> str:
    """The C header with value references and the variable table (see fmus/common/glue.h)."""
    causality = {"parameter": "CAUS_PARAMETER", "input": "CAUS_INPUT", "output": "CAUS_OUTPUT"}
    vtype = {"Real": "VT_REAL", "Integer": "VT_INTEGER", "Boolean": "VT_BOOLEAN"}
    lines = [
        f"/* Generated by {GENERATOR} from {spec.name}/model.toml. Do not edit. */",
        "#ifndef MODEL_VARIABLES_H",
        "#define MODEL_VARIABLES_H",
        f'#define MODEL_IDENTIFIER "{spec.name}"',
        f'#define MODEL_GUID "{model_guid}"',
        f"#define N_VARIABLES {len(spec.variables)}",
        "enum {",
        *[f"    VR_{v.name} = {v.value_reference}," for v in spec.variables],
        "};",
        *[f"#define COUNT_{name} {count}" for name, count in spec.families],
        "static const VariableInfo VARIABLES[N_VARIABLES] = {",
    ]
    for v in spec.variables:
        start = _c_double(v.start if v.start is not None else 0.0)
        lines.append(
            f'    {{"{v.name}", {vtype[v.type]}, {causality[v.causality]}, {start}, '
            f"{int(v.min is not None)}, {int(v.max is not None)}, "
            f"{_c_double(v.min or 0.0)}, {_c_double(v.max or 0.0)}}},"
        )
    lines += ["};", "#endif", ""]
    return "\n".join(lines)


def _format_number(value: float, vtype: str) -> str:
    if vtype == "Boolean":
        return "true" if value else "false"
    if vtype == "Integer":
        return str(int(value))
    return repr(float(value))


def generate_model_description(
    spec: ModelSpec, model_guid: str, source_files: list[str] | None = None
) -> str:
    """modelDescription.xml (FMI 2.0 co-simulation) for the spec."""
    root = ET.Element(
        "fmiModelDescription",
        fmiVersion="2.0",
        modelName=spec.name,
        guid=model_guid,
        description=spec.description,
        generationTool=f"{GENERATOR} {generator_version()}",
        generationDateAndTime=generation_date(spec),
        variableNamingConvention="flat",
        numberOfEventIndicators="0",
    )
    cosim = ET.SubElement(
        root,
        "CoSimulation",
        modelIdentifier=spec.name,
        canHandleVariableCommunicationStepSize="true",
        canGetAndSetFMUstate="true",
        canSerializeFMUstate="true",
    )
    if source_files:
        listed = ET.SubElement(cosim, "SourceFiles")
        for name in source_files:
            ET.SubElement(listed, "File", name=name)
    _unit_definitions(root, spec)
    categories = ET.SubElement(root, "LogCategories")
    for category in ("logStatusError", "logStatusWarning"):
        ET.SubElement(categories, "Category", name=category)
    ET.SubElement(root, "DefaultExperiment", startTime="0.0", stepSize=repr(spec.step_size))
    _model_variables(root, spec)
    _model_structure(root, spec)
    ET.indent(root)
    return '<?xml version="1.0" encoding="UTF-8"?>\n' + ET.tostring(root, encoding="unicode") + "\n"


def _unit_definitions(root: ET.Element, spec: ModelSpec) -> None:
    """<UnitDefinitions>: every unit the variables use, in SI base units, with display units."""
    used = sorted({v.unit for v in spec.variables if v.unit is not None})
    if used:
        units = ET.SubElement(root, "UnitDefinitions")
        for name in used:
            unit = ET.SubElement(units, "Unit", name=name)
            ET.SubElement(unit, "BaseUnit", {k: str(e) for k, e in _UNITS[name].items()})
            for display, factor in _DISPLAY_UNITS.get(name, []):
                ET.SubElement(unit, "DisplayUnit", name=display, factor=repr(1.0 / factor))


def _model_variables(root: ET.Element, spec: ModelSpec) -> None:
    """<ModelVariables>: one ScalarVariable per variable, in value-reference order."""
    variables = ET.SubElement(root, "ModelVariables")
    for v in spec.variables:
        attrs = {
            "name": v.name,
            "valueReference": str(v.value_reference),
            "description": v.description,
            "causality": v.causality,
            "variability": v.variability,
        }
        if v.causality == "parameter":
            attrs["initial"] = "exact"
        element = ET.SubElement(variables, "ScalarVariable", attrs)
        ET.SubElement(element, v.type, _type_attributes(v))


def _type_attributes(v: Variable) -> dict[str, str]:
    """The attributes of a variable's type element: unit, min, max, start (those it has)."""
    type_attrs: dict[str, str] = {}
    if v.unit is not None:
        type_attrs["unit"] = v.unit
    if v.min is not None:
        type_attrs["min"] = _format_number(v.min, v.type)
    if v.max is not None:
        type_attrs["max"] = _format_number(v.max, v.type)
    if v.start is not None:
        type_attrs["start"] = _format_number(v.start, v.type)
    return type_attrs


def _model_structure(root: ET.Element, spec: ModelSpec) -> None:
    """<ModelStructure>: the outputs and their initial dependencies.

    Outputs change only in fmi2DoStep (the glue recomputes them from the state there), so in
    step mode no output depends directly on an input: empty dependencies, no false algebraic
    loop for a master. In initialisation mode an output follows the parameters and the inputs
    its model.toml lists in depends_on."""
    structure = ET.SubElement(root, "ModelStructure")
    index = {v.name: i + 1 for i, v in enumerate(spec.variables)}
    outputs_list = [v for v in spec.variables if v.causality == "output"]
    if outputs_list:
        outputs = ET.SubElement(structure, "Outputs")
        initial = ET.SubElement(structure, "InitialUnknowns")
        parameters = [index[v.name] for v in spec.variables if v.causality == "parameter"]
        for v in outputs_list:
            ET.SubElement(outputs, "Unknown", index=str(index[v.name]), dependencies="")
            known = sorted({*parameters, *(index[name] for name in v.depends_on)})
            ET.SubElement(
                initial,
                "Unknown",
                index=str(index[v.name]),
                dependencies=" ".join(map(str, known)),
            )
