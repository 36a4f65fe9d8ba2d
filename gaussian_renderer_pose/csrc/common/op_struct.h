// Turns an X-macro argument list into a struct with one field per argument, the matching part of
// a TORCH_LIBRARY schema string, and the reading/writing of that struct from/to the dispatcher's
// boxed stack. This is what lets ../ops.h state the arguments of each native op once. Host only.
//
// A list is a macro LIST(X) calling X(kind, name) once per argument, in schema order. Kinds:
//   kind       C++ field                        schema type
//   Tensor     at::Tensor                       Tensor
//   OptTensor  at::Tensor (undefined = None)    Tensor?
//   Int        int64_t                          int
//   Float      double                           float
//   Bool       bool                             bool
#pragma once

#include <ATen/ATen.h>
#include <ATen/core/ivalue.h>
#include <ATen/core/stack.h>
#include <torch/library.h>

#include <cstddef>
#include <string>

namespace grp {
namespace op_kind {

struct Tensor {
  using type = at::Tensor;
  static constexpr const char* schema = "Tensor";
  static type read(const c10::IValue& v) { return v.toTensor(); }
  static c10::IValue write(const type& t) { return t; }
};
struct OptTensor {
  using type = at::Tensor;
  static constexpr const char* schema = "Tensor?";
  static type read(const c10::IValue& v) { return v.isNone() ? at::Tensor() : v.toTensor(); }
  static c10::IValue write(const type& t) { return t.defined() ? c10::IValue(t) : c10::IValue(); }
};
struct Int {
  using type = int64_t;
  static constexpr const char* schema = "int";
  static type read(const c10::IValue& v) { return v.toInt(); }
  static c10::IValue write(type x) { return x; }
};
struct Float {
  using type = double;
  static constexpr const char* schema = "float";
  static type read(const c10::IValue& v) { return v.toDouble(); }
  static c10::IValue write(type x) { return x; }
};
struct Bool {
  using type = bool;
  static constexpr const char* schema = "bool";
  static type read(const c10::IValue& v) { return v.toBool(); }
  static c10::IValue write(type x) { return x; }
};

inline void append_schema(std::string& s, const char* type, const char* name) {
  if (!s.empty()) s += ", ";
  s += type;
  s += ' ';
  s += name;
}

}  // namespace op_kind

#define GRP_OP_FIELD(kind, name) ::grp::op_kind::kind::type name;
#define GRP_OP_COUNT(kind, name) +1
#define GRP_OP_SCHEMA(kind, name) \
  ::grp::op_kind::append_schema(s, ::grp::op_kind::kind::schema, #name);
#define GRP_OP_READ(kind, name) r.name = ::grp::op_kind::kind::read(*it++);
#define GRP_OP_WRITE(kind, name) stack.push_back(::grp::op_kind::kind::write(name));

// struct Name { <one field per entry of LIST> }, plus:
//   kSize     number of entries;
//   schema()  "Tensor means3D, Tensor opacities, ..." (an argument or return list of a schema);
//   read(it)  the struct from kSize consecutive IValues starting at it;
//   write(st) pushes the fields onto a stack, in order.
#define GRP_OP_STRUCT(Name, LIST)                                                    \
  struct Name {                                                                      \
    LIST(GRP_OP_FIELD)                                                               \
    static constexpr size_t kSize = 0 LIST(GRP_OP_COUNT);                            \
    static std::string schema() {                                                    \
      std::string s;                                                                 \
      LIST(GRP_OP_SCHEMA)                                                            \
      return s;                                                                      \
    }                                                                                \
    static Name read(const c10::IValue* it) {                                        \
      Name r;                                                                        \
      LIST(GRP_OP_READ)                                                              \
      return r;                                                                      \
    }                                                                                \
    void write(torch::jit::Stack& stack) const { LIST(GRP_OP_WRITE) }                \
  }

// "name(<In::schema()>) -> (<Out::schema()>)"
template <typename In, typename Out>
std::string op_schema(const char* name) {
  return std::string(name) + "(" + In::schema() + ") -> (" + Out::schema() + ")";
}

// Boxed kernel calling `Out kernel(const In&)`: pops In from the stack, pushes Out.
template <auto Kernel>
struct BoxedKernel;

template <typename Out, typename In, Out (*Kernel)(const In&)>
struct BoxedKernel<Kernel> {
  static void call(const c10::OperatorHandle& op, torch::jit::Stack* stack) {
    const c10::FunctionSchema& schema = op.schema();
    TORCH_INTERNAL_ASSERT(schema.arguments().size() == In::kSize &&
                              schema.returns().size() == Out::kSize,
                          "kernel registered for ", schema.name(), " does not match its schema");
    const In in = In::read(stack->data() + stack->size() - In::kSize);
    torch::jit::drop(*stack, In::kSize);
    Kernel(in).write(*stack);
  }
};

// For TORCH_LIBRARY_IMPL: m.impl("op", boxed_kernel<&op_cpu>()).
template <auto Kernel>
torch::CppFunction boxed_kernel() {
  return torch::CppFunction::makeFromBoxedFunction<&BoxedKernel<Kernel>::call>();
}

}  // namespace grp
