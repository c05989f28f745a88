// Channels and server credentials (rpc_channel.h): plain text or mutual TLS, and who may call what.
#include "stage/common/rpc_channel.h"

#include <grpcpp/create_channel.h>
#include <grpcpp/security/auth_context.h>
#include <grpcpp/security/auth_metadata_processor.h>
#include <grpcpp/security/credentials.h>
#include <grpcpp/security/server_credentials.h>
#include <grpcpp/security/tls_certificate_provider.h>
#include <grpcpp/security/tls_credentials_options.h>
#include <grpcpp/support/channel_arguments.h>
#include <openssl/pem.h>
#include <openssl/x509.h>
#include <openssl/x509v3.h>

#include <array>
#include <cstdio>
#include <map>
#include <mutex>
#include <vector>

#include "absl/status/statusor.h"
#include "absl/strings/match.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_join.h"
#include "stage/common/logging.h"

namespace stage {
namespace {

constexpr absl::string_view kUriPrefix = "fastage:";

template <typename T, void (*Free)(T*)>
struct Freer {
  void operator()(T* p) const { Free(p); }
};
using X509Ptr = std::unique_ptr<X509, Freer<X509, X509_free>>;
using KeyPtr = std::unique_ptr<EVP_PKEY, Freer<EVP_PKEY, EVP_PKEY_free>>;
using StorePtr = std::unique_ptr<X509_STORE, Freer<X509_STORE, X509_STORE_free>>;
using StoreCtxPtr = std::unique_ptr<X509_STORE_CTX, Freer<X509_STORE_CTX, X509_STORE_CTX_free>>;

// Opens `path` for reading; InvalidArgument names the field and the file.
absl::StatusOr<FILE*> Open(absl::string_view field, const std::string& path) {
  if (path.empty()) return absl::InvalidArgumentError(absl::StrCat(field, ": mutual TLS needs a PEM file"));
  FILE* f = std::fopen(path.c_str(), "r");
  if (f == nullptr) return absl::InvalidArgumentError(absl::StrCat(field, ": cannot read ", path));
  return f;
}

absl::StatusOr<X509Ptr> ReadCertificate(absl::string_view field, const std::string& path) {
  auto f = Open(field, path);
  if (!f.ok()) return f.status();
  X509Ptr cert(PEM_read_X509(*f, nullptr, nullptr, nullptr));
  std::fclose(*f);
  if (!cert) return absl::InvalidArgumentError(absl::StrCat(field, ": ", path, " holds no PEM certificate"));
  return cert;
}

bool ValidIdentity(absl::string_view id) {
  if (id == "controller" || id == "sim" || id == "console") return true;
  for (absl::string_view kind : {"camera/", "light/", "worker/", "operator/", "observer/"}) {
    if (absl::StartsWith(id, kind) && id.size() > kind.size()) return true;
  }
  return false;
}

// The identity a certificate names: its URI SAN fastage:<identity>, else its common name.
std::string CertificateIdentity(X509* cert) {
  auto* names = static_cast<GENERAL_NAMES*>(X509_get_ext_d2i(cert, NID_subject_alt_name, nullptr, nullptr));
  std::string identity;
  for (int i = 0; names != nullptr && i < sk_GENERAL_NAME_num(names) && identity.empty(); ++i) {
    const GENERAL_NAME* name = sk_GENERAL_NAME_value(names, i);
    if (name->type != GEN_URI) continue;
    const auto* data = reinterpret_cast<const char*>(ASN1_STRING_get0_data(name->d.uniformResourceIdentifier));
    absl::string_view uri(data, static_cast<size_t>(ASN1_STRING_length(name->d.uniformResourceIdentifier)));
    if (absl::StartsWith(uri, kUriPrefix)) identity = std::string(uri.substr(kUriPrefix.size()));
  }
  GENERAL_NAMES_free(names);
  if (!identity.empty()) return identity;
  std::array<char, 256> cn{};
  if (X509_NAME_get_text_by_NID(X509_get_subject_name(cert), NID_commonName, cn.data(), cn.size()) > 0) {
    return cn.data();
  }
  return "";
}

// Checks the certificate against the CA (chain and dates) and the key against the certificate; returns the identity.
absl::StatusOr<std::string> CheckFiles(const TransportSecurity& s) {
  auto ca = ReadCertificate("ca_file", s.ca_file);
  if (!ca.ok()) return ca.status();
  auto cert = ReadCertificate("cert_file", s.cert_file);
  if (!cert.ok()) return cert.status();
  auto f = Open("key_file", s.key_file);
  if (!f.ok()) return f.status();
  KeyPtr key(PEM_read_PrivateKey(*f, nullptr, nullptr, nullptr));
  std::fclose(*f);
  if (!key) return absl::InvalidArgumentError(absl::StrCat("key_file: ", s.key_file, " holds no PEM private key"));
  if (X509_check_private_key(cert->get(), key.get()) != 1) {
    return absl::InvalidArgumentError(
        absl::StrCat("key_file: ", s.key_file, " is not the key of the certificate ", s.cert_file));
  }
  // Every certificate of the CA file (a bundle, during a CA's rollover), as gRPC reads it.
  StorePtr store(X509_STORE_new());
  StoreCtxPtr ctx(X509_STORE_CTX_new());
  if (!store || !ctx || X509_STORE_load_file(store.get(), s.ca_file.c_str()) != 1 ||
      X509_STORE_CTX_init(ctx.get(), store.get(), cert->get(), nullptr) != 1) {
    return absl::InvalidArgumentError(absl::StrCat("ca_file: ", s.ca_file, " could not be loaded as CA certificates"));
  }
  if (X509_verify_cert(ctx.get()) != 1) {
    return absl::InvalidArgumentError(absl::StrCat("cert_file: ", s.cert_file, " does not verify against the CA ",
                                                   s.ca_file, ": ",
                                                   X509_verify_cert_error_string(X509_STORE_CTX_get_error(ctx.get()))));
  }
  std::string identity = CertificateIdentity(cert->get());
  if (!ValidIdentity(identity)) {
    return absl::InvalidArgumentError(absl::StrCat(
        "cert_file: ", s.cert_file, " names \"", identity,
        "\", not a FaStage identity (controller, sim, camera/ID, light/ID, worker/ID, operator/NAME, observer/NAME; "
        "scripts/make-test-certs)"));
  }
  return identity;
}

struct ProcessSecurity {
  std::mutex mutex;
  TransportSecurity security;  // guarded by mutex
  std::string identity;        // guarded by mutex
};

ProcessSecurity& Process() {
  static ProcessSecurity* process = new ProcessSecurity();
  return *process;
}

// One watcher per set of files, shared by every channel and server that uses them while any does (each watcher is a
// thread that reads the files every interval).
std::shared_ptr<grpc::experimental::FileWatcherCertificateProvider> Provider(const TransportSecurity& s) {
  static std::mutex mutex;
  static auto* providers =
      new std::map<std::string, std::weak_ptr<grpc::experimental::FileWatcherCertificateProvider>>();
  const std::string key = absl::StrCat(s.ca_file, "\n", s.cert_file, "\n", s.key_file, "\n", s.reload_interval_s);
  std::lock_guard<std::mutex> lock(mutex);
  std::shared_ptr<grpc::experimental::FileWatcherCertificateProvider> provider = (*providers)[key].lock();
  if (provider == nullptr) {  // none yet, or every user of the last one is gone
    provider = std::make_shared<grpc::experimental::FileWatcherCertificateProvider>(
        s.key_file, s.cert_file, s.ca_file, static_cast<unsigned>(s.reload_interval_s));
    (*providers)[key] = provider;
  }
  return provider;
}

// Every call to a mutual-TLS server, before its handler: the caller's identity against the method.
class Authorizer final : public grpc::AuthMetadataProcessor {
 public:
  bool IsBlocking() const override { return false; }

  grpc::Status Process(const InputMetadata& metadata, grpc::AuthContext* context, OutputMetadata*,
                       OutputMetadata*) override {
    auto path = metadata.find(":path");
    const std::string method =
        path == metadata.end() ? std::string() : std::string(path->second.data(), path->second.size());
    const std::string identity = PeerIdentity(*context);
    std::string why;
    if (AuthorizeCall(identity, method, &why)) return grpc::Status::OK;
    const std::string who = identity.empty() ? "an unauthenticated peer" : identity;
    Logger("rpc.auth")->warn("refused {} calling {}: {}", who, method, why);
    return grpc::Status(grpc::StatusCode::PERMISSION_DENIED, absl::StrCat(who, " may not call ", method, ": ", why));
  }
};

}  // namespace

namespace {

// Validate()'s checks; the identity the certificate names ("" in plain text).
absl::StatusOr<std::string> CheckedIdentity(const TransportSecurity& s) {
  if (s.reload_interval_s < 1 || s.reload_interval_s > 3600) {
    return absl::InvalidArgumentError("reload_interval_s must be 1..3600");
  }
  if (s.mode == TransportSecurity::Mode::kMutualTls) return CheckFiles(s);
  if (!s.ca_file.empty() || !s.cert_file.empty() || !s.key_file.empty()) {
    return absl::InvalidArgumentError("plain text takes no certificate files (set mutual TLS to use them)");
  }
  return std::string();
}

}  // namespace

absl::Status TransportSecurity::Validate() const { return CheckedIdentity(*this).status(); }

absl::Status SetTransportSecurity(const TransportSecurity& security) {
  auto identity = CheckedIdentity(security);
  if (!identity.ok()) return identity.status();
  ProcessSecurity& p = Process();
  std::lock_guard<std::mutex> lock(p.mutex);
  p.security = security;
  p.identity = *identity;
  return absl::OkStatus();
}

TransportSecurity ProcessTransportSecurity() {
  ProcessSecurity& p = Process();
  std::lock_guard<std::mutex> lock(p.mutex);
  return p.security;
}

std::string DescribeTransportSecurity() {
  ProcessSecurity& p = Process();
  std::lock_guard<std::mutex> lock(p.mutex);
  if (p.security.mode == TransportSecurity::Mode::kPlainText) return "plain text, loopback only";
  return absl::StrCat("mutual TLS as ", p.identity, ", CA ", p.security.ca_file);
}

std::shared_ptr<grpc::Channel> MakeChannel(const std::string& address) {
  return MakeChannel(address, grpc::ChannelArguments(), ProcessTransportSecurity());
}

std::shared_ptr<grpc::Channel> MakeChannel(const std::string& address, const grpc::ChannelArguments& args) {
  return MakeChannel(address, args, ProcessTransportSecurity());
}

std::shared_ptr<grpc::Channel> MakeChannel(const std::string& address, const grpc::ChannelArguments& args,
                                           const TransportSecurity& security) {
  if (security.mode == TransportSecurity::Mode::kPlainText) {
    return grpc::CreateCustomChannel(address, grpc::InsecureChannelCredentials(), args);
  }
  grpc::experimental::TlsChannelCredentialsOptions options;
  options.set_certificate_provider(Provider(security));
  options.watch_root_certs();
  options.watch_identity_key_cert_pairs();
  // The server's certificate is checked against the CA and the address dialled (its IP or DNS SANs).
  options.set_verify_server_certs(true);
  return grpc::CreateCustomChannel(address, grpc::experimental::TlsCredentials(options), args);
}

std::shared_ptr<grpc::ServerCredentials> MakeServerCredentials() {
  return MakeServerCredentials(ProcessTransportSecurity());
}

std::shared_ptr<grpc::ServerCredentials> MakeServerCredentials(const TransportSecurity& security) {
  // (An AuthMetadataProcessor on plain-text credentials aborts the process in gRPC 1.51: only TLS gets one.)
  if (security.mode == TransportSecurity::Mode::kPlainText) return grpc::InsecureServerCredentials();
  grpc::experimental::TlsServerCredentialsOptions options(Provider(security));
  options.watch_root_certs();
  options.watch_identity_key_cert_pairs();
  options.set_cert_request_type(GRPC_SSL_REQUEST_AND_REQUIRE_CLIENT_CERTIFICATE_AND_VERIFY);
  auto credentials = grpc::experimental::TlsServerCredentials(options);
  credentials->SetAuthMetadataProcessor(std::make_shared<Authorizer>());
  return credentials;
}

std::string PeerIdentity(const grpc::AuthContext& context) {
  if (!context.IsPeerAuthenticated()) return "";
  for (const grpc::string_ref& san : context.FindPropertyValues(GRPC_X509_SAN_PROPERTY_NAME)) {
    absl::string_view v(san.data(), san.size());
    if (absl::StartsWith(v, kUriPrefix)) return std::string(v.substr(kUriPrefix.size()));
  }
  for (const grpc::string_ref& cn : context.FindPropertyValues(GRPC_X509_CN_PROPERTY_NAME)) {
    return std::string(cn.data(), cn.size());
  }
  return "";
}

bool AuthorizeCall(absl::string_view identity, absl::string_view method, std::string* why) {
  // "/stage.v1.LightNode/Arm" -> service "stage.v1.LightNode", call "Arm"; "camera/mv-01" -> kind "camera".
  const size_t slash = method.rfind('/');
  if (method.empty() || method[0] != '/' || slash == 0 || slash == absl::string_view::npos) {
    *why = "not a method path";
    return false;
  }
  const absl::string_view service = method.substr(1, slash - 1), call = method.substr(slash + 1);
  const absl::string_view kind = identity.substr(0, identity.find('/'));
  if (identity.empty()) {
    *why = "the peer presented no certificate";
    return false;
  }
  if (!ValidIdentity(identity)) {
    *why = absl::StrCat("its certificate names \"", identity, "\", not a FaStage identity");
    return false;
  }
  const bool reads = absl::StartsWith(call, "Get") || absl::StartsWith(call, "List") ||
                     absl::StartsWith(call, "Watch") || absl::StartsWith(call, "Check") ||
                     absl::StartsWith(call, "Export");
  std::vector<absl::string_view> allowed;
  if (service == "grpc.health.v1.Health") return true;
  if (service == "stage.v1.LightNode" || service == "stage.v1.ProcessingWorker" || service == "stage.v1.NodeClock") {
    allowed = {"controller"};
  } else if (service == "stage.v1.CameraNode") {
    allowed = reads ? std::vector<absl::string_view>{"controller", "operator", "observer", "sim"}
                    : std::vector<absl::string_view>{"controller"};
  } else if (service == "stage.v1.StageController") {
    // The console (stage-console) acts for its logged-in users, whose roles it checks itself.
    allowed = reads ? std::vector<absl::string_view>{"operator", "observer", "sim", "console"}
                    : std::vector<absl::string_view>{"operator", "console"};
  } else if (service == "stage.v1.SimWorld") {
    // Devices join the world and run its bus; faults and ground truth (files written where the request says) are the
    // operator's and the controller's.
    const bool devices = call != "InjectFault" && call != "WriteGroundTruth";
    allowed = devices ? std::vector<absl::string_view>{"sim", "camera", "light", "controller", "operator"}
                      : std::vector<absl::string_view>{"sim", "controller", "operator"};
  } else {
    *why = absl::StrCat("no identity may call ", service, " (not a FaStage service)");
    return false;
  }
  for (absl::string_view a : allowed) {
    if (kind == a) return true;
  }
  *why = absl::StrCat(
      service,
      (service == "stage.v1.CameraNode" || service == "stage.v1.StageController") && !reads ? " (its commands)" : "",
      " takes calls from ", absl::StrJoin(allowed, ", "), " only");
  return false;
}

}  // namespace stage
