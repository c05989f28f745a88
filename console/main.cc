// stage-console: the stage's console in a browser. A gRPC client of the controller (a console that fails never touches
// the stage) serving pages, a JSON API and one event stream over HTTP, behind a login (docs/console.md).
#include <termios.h>
#include <unistd.h>

#include <filesystem>
#include <iostream>

#include "alarms.h"
#include "console_server.h"
#include "event_log.h"
#include "log_tail.h"
#include "stage/common/cli.h"
#include "stage/common/file_util.h"
#include "stage/common/logging.h"
#include "stage/common/rig.h"
#include "stage/common/rpc_server.h"
#include "stage/common/shutdown.h"
#include "stage/common/stage_locator.h"
#include "stage/common/status.h"
#include "stage_link.h"
#include "users.h"

namespace {

constexpr const char* kProgram = "stage-console";

// A password from stdin: one line, not echoed when stdin is a terminal.
std::string ReadPassword() {
  const bool tty = isatty(STDIN_FILENO) != 0;
  termios saved{};
  if (tty) {
    std::cerr << "password: " << std::flush;
    tcgetattr(STDIN_FILENO, &saved);
    termios quiet = saved;
    quiet.c_lflag &= ~static_cast<tcflag_t>(ECHO);
    tcsetattr(STDIN_FILENO, TCSANOW, &quiet);
  }
  std::string password;
  std::getline(std::cin, password);
  if (tty) {
    tcsetattr(STDIN_FILENO, TCSANOW, &saved);
    std::cerr << "\n";
  }
  return password;
}

int AddUserCommand(const std::string& users_file, const std::string& name, const std::string& role_name) {
  auto role = stage::console::ParseRole(role_name);
  if (!role.ok()) return stage::ReportFatal(kProgram, role.status());
  if (users_file.empty()) {
    return stage::ReportFatal(kProgram, absl::InvalidArgumentError("--users: the users file to write is needed"));
  }
  if (auto s = stage::console::AddUser(users_file, name, *role, ReadPassword()); !s.ok()) {
    return stage::ReportFatal(kProgram, s);
  }
  std::cout << "user " << name << " (" << role_name << ") written to " << users_file << "\n";
  return 0;
}

// Every flag of the program.
struct ConsoleFlags {
  stage::CommonFlags common;
  stage::StageLocator where;
  stage::console::ConsoleServerOptions server;
  stage::console::StageLinkOptions link;
  std::string port_file;
  std::string users_file;
  std::string alarm_db;
  std::vector<std::string> tail;
  double session_hours = 12;
};

void AddFlags(CLI::App& app, ConsoleFlags* f) {
  stage::AddCommonFlags(app, &f->common, /*serves=*/false);
  app.add_option("--controller", f->where.controller,
                 "Controller address host:port (default: the rig's controller.listen with --config, "
                 "$FASTAGE_CONTROLLER, or the stage-sim endpoint file)");
  app.add_option("--endpoints", f->where.endpoints,
                 "stage-sim endpoint file (default: $FASTAGE_ENDPOINTS or /tmp/fastage-0/stage-sim/endpoints.json)");
  app.add_option("--as", f->where.identity,
                 "Identity to present when the rig says mutual TLS (default: $FASTAGE_IDENTITY, else console)");
  app.add_option("--listen", f->server.listen, "Where to serve HTTP, host:port (port 0 picks a free one)")
      ->capture_default_str();
  app.add_option("--port-file", f->port_file, "Once serving, write the bound host:port to this file");
  app.add_option("--metrics-listen", f->common.metrics_listen,
                 "Where to serve Prometheus metrics over HTTP, host:port (port 0 picks a free one); empty: none");
  app.add_option("--metrics-port-file", f->common.metrics_port_file,
                 "After binding the metrics endpoint, write its host:port to this file");
  app.add_option("--users", f->users_file,
                 "Users file (NAME:ROLE:pbkdf2-sha256:...; `stage-console users add` writes it)");
  app.add_option("--alarm-db", f->alarm_db,
                 "SQLite file of the alarms and their acknowledgements (default: console-alarms.sqlite beside the "
                 "users file)");
  app.add_option("--tail-log", f->tail,
                 "A log file, or a directory whose *.log files, the log page follows; repeatable");
  app.add_option("--max-streams", f->server.max_streams, "Event streams (open pages) served at once")
      ->capture_default_str();
  f->session_hours = f->server.session_lifetime_s / 3600.0;
  app.add_option("--session-hours", f->session_hours, "A login lasts this long after its last use")
      ->capture_default_str();
  app.add_option("--thermal-alarm", f->link.alarms.thermal_load,
                 "Raise a thermal alarm when a light node's armed table reaches this much of its thermal limit")
      ->capture_default_str();
}

// Serves the console until SIGINT or SIGTERM; the exit code.
int Serve(ConsoleFlags& f) {
  f.server.session_lifetime_s = static_cast<int>(f.session_hours * 3600);
  if (f.users_file.empty()) {
    return stage::ReportFatal(
        kProgram, absl::InvalidArgumentError("--users: the console needs a users file (stage-console users add NAME "
                                             "--role operator --users FILE)"));
  }
  auto book = stage::console::UserBook::Load(f.users_file);
  if (!book.ok()) return stage::ReportFatal(kProgram, book.status());
  if (book->size() == 0) {
    return stage::ReportFatal(kProgram, absl::InvalidArgumentError("users file " + f.users_file + " has no users"));
  }
  if (auto s = stage::UseStageSecurity(&f.where, "console"); !s.ok()) return stage::ReportFatal(kProgram, s);
  auto controller = stage::ResolveController(f.where);
  if (!controller.ok()) return stage::ReportFatal(kProgram, controller.status());
  f.link.controller = *controller;
  if (auto s = f.link.Validate(); !s.ok()) return stage::ReportFatal(kProgram, s);
  const stage::console::LogTailOptions tail{.paths = f.tail};
  if (auto s = tail.Validate(); !s.ok()) return stage::ReportFatal(kProgram, s);
  if (f.alarm_db.empty()) {
    f.alarm_db = (std::filesystem::path(f.users_file).parent_path() / "console-alarms.sqlite").string();
  }
  auto alarms = stage::console::AlarmBook::Open(f.alarm_db);
  if (!alarms.ok()) return stage::ReportFatal(kProgram, alarms.status());

  stage::console::EventLog events(4096);
  stage::console::StageLink link(f.link, &events, alarms->get());
  stage::console::LogTail logs(tail, &events);
  auto started = stage::console::ConsoleServer::Start(
      f.server, {.link = &link, .events = &events, .alarms = alarms->get(), .logs = &logs, .users = &*book});
  if (!started.ok()) return stage::ReportFatal(kProgram, started.status());
  link.Start();
  logs.Start();
  auto metrics = stage::StartMetrics(kProgram, f.common);
  if (!metrics.ok()) return stage::ReportFatal(kProgram, metrics.status());
  // Last: the port file says the console is ready.
  if (!f.port_file.empty()) {
    if (auto s = stage::WriteFileAtomically(f.port_file, (*started)->address() + "\n"); !s.ok()) {
      return stage::ReportFatal(kProgram, stage::Annotate(s, "--port-file"));
    }
  }
  auto log = stage::Logger("console");
  log->info("serving the console on {} for the controller at {} ({} users, alarms in {})", (*started)->url(),
            *controller, book->size(), f.alarm_db);
  std::string host;
  int port = 0;
  (void)stage::ParseHostPort(f.server.listen, &host, &port);  // checked by ConsoleServerOptions::Validate
  if (!stage::IsLoopbackHost(host)) {
    log->warn(
        "{} is not a loopback address: passwords and the session cookie cross the network in plain HTTP; put "
        "the console behind a TLS proxy",
        host);
  }
  stage::WaitForShutdownSignal();
  log->info("stopping");
  started->reset();
  logs.Stop();
  link.Stop();
  return 0;
}

}  // namespace

int main(int argc, char** argv) {
  stage::BlockShutdownSignals();
  CLI::App app{
      "The FaStage console in a browser: serves the stage at a glance, previews, takes, timing, alarms and logs over "
      "HTTP to logged-in users (observers read; operators arm, capture and reset the emergency stop), as a client of "
      "the controller.",
      kProgram};
  ConsoleFlags flags;
  AddFlags(app, &flags);
  CLI::App* users = app.add_subcommand("users", "Manage the users file");
  CLI::App* add = users->add_subcommand("add", "Add or replace a user; the password is read from stdin (one line)");
  std::string user_name, user_role = "observer";
  add->add_option("name", user_name, "User name")->required();
  add->add_option("--role", user_role, "observer or operator")->capture_default_str();
  users->require_subcommand(1);
  // --users and the other options of the program may come after the subcommand too.
  users->fallthrough();
  add->fallthrough();

  if (auto code = stage::ParseCommandLine(app, argc, argv)) return *code;
  if (add->parsed()) return AddUserCommand(flags.users_file, user_name, user_role);
  if (auto s = stage::InitLogging(kProgram, flags.common.log_level); !s.ok()) return stage::ReportFatal(kProgram, s);
  return Serve(flags);
}
