// An Unreal Engine 5 actor component that streams the headset and both motion controllers to an EgoPose server
// and keeps the newest served body (joints in Unreal's world, cm), drawn as debug lines. A starting point for a
// C++ client: the wire format and the frame conversions are EgoPoseProtocol.h (compiled and tested by the
// project); this Unreal glue is documentation, NOT compiled or run by the project's tests (no Unreal here).
//
// Build.cs: PublicDependencyModuleNames.AddRange(new[] { "Core", "CoreUObject", "Engine", "WebSockets",
// "HeadMountedDisplay" }); put msgpack-cxx's include folder (header-only) on PublicIncludePaths.
#pragma once

#include "Components/ActorComponent.h"
#include "CoreMinimal.h"
#include "EgoPoseProtocol.h"
#include "EgoPoseComponent.generated.h"

class IWebSocket;

UCLASS(ClassGroup = (EgoPose), meta = (BlueprintSpawnableComponent))
class UEgoPoseComponent : public UActorComponent {
    GENERATED_BODY()

   public:
    UEgoPoseComponent();

    // ws://HOST:PORT/ws of the server; the session is appended as ?session=.
    UPROPERTY(EditAnywhere, Category = "EgoPose") FString Url = TEXT("ws://127.0.0.1:8765/ws");
    UPROPERTY(EditAnywhere, Category = "EgoPose") FString Session = TEXT("default");
    UPROPERTY(EditAnywhere, Category = "EgoPose") FString Model;  // empty: the session's or the server's default
    UPROPERTY(EditAnywhere, Category = "EgoPose") bool bDrawSkeleton = true;

    // A returning wearer's body (PROTOCOL.md §4.2): the 21 bone lengths (m) kept from their last session (load them
    // from your SaveGame before BeginPlay), given first after every welcome; empty: the server estimates the body.
    UPROPERTY(EditAnywhere, BlueprintReadWrite, Category = "EgoPose") TArray<float> KeptBoneLengths;

    // The newest body the server said is measured and was not given (after RequestBody): save it with the
    // wearer's profile and put it in KeptBoneLengths at their next session.
    UPROPERTY(BlueprintReadOnly, Category = "EgoPose") TArray<float> MeasuredBoneLengths;

    // The session's model and every servable one, from the server's `models` (after the welcome, after SelectModel).
    UPROPERTY(BlueprintReadOnly, Category = "EgoPose") FString ActiveModel;
    UPROPERTY(BlueprintReadOnly, Category = "EgoPose") TArray<FString> ModelNames;

    // The SHA-256 of the active model's file and of its visual encoder's (empty for procedural): which weights
    // answered this session (PROTOCOL.md §model-digests). Logged on every change; keep them with a bug report.
    UPROPERTY(BlueprintReadOnly, Category = "EgoPose") FString ActiveModelSha256;
    UPROPERTY(BlueprintReadOnly, Category = "EgoPose") FString ActiveEncoderSha256;

    // The newest served joints (22, SMPL order of PROTOCOL.md §3), Unreal world space, cm.
    UPROPERTY(BlueprintReadOnly, Category = "EgoPose") TArray<FVector> Joints;

    // Which feet the server holds planted in the newest pose (left, right; both false for a model that plants no
    // feet): a retargeted mesh pins them with egopose::FootPins (PROTOCOL.md §planted-feet), drawn as a dot here.
    UPROPERTY(BlueprintReadOnly, Category = "EgoPose") bool bLeftFootPlanted = false;
    UPROPERTY(BlueprintReadOnly, Category = "EgoPose") bool bRightFootPlanted = false;

    UFUNCTION(BlueprintCallable, Category = "EgoPose") void SelectModel(const FString& Name);

    // Ask the server for the wearer's body (get_body); a measured answer lands in MeasuredBoneLengths.
    UFUNCTION(BlueprintCallable, Category = "EgoPose") void RequestBody();

   protected:
    virtual void BeginPlay() override;
    virtual void EndPlay(const EEndPlayReason::Type Reason) override;
    virtual void TickComponent(float DeltaTime, ELevelTick TickType, FActorComponentTickFunction* ThisTick) override;

   private:
    void Connect();
    void OnRawMessage(const void* Data, SIZE_T Size, SIZE_T BytesRemaining);
    void SendHmd();
    void Send(const msgpack::sbuffer& Buffer);

    TSharedPtr<IWebSocket> Socket;
    TArray<uint8> Partial;  // a message arriving in several frames
    bool bWelcomed = false;
    int64 Seq = 0;
    double ReconnectAt = 0;  // FPlatformTime::Seconds() of the next attempt after a drop
    double Backoff = 0.25;
};
